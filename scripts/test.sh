#!/usr/bin/env bash
# The test command (README, .ci/run): set up, make sure headless Chromium is there for the
# viewer test, run the suite. Extra arguments go to pytest (e.g. --run-slow, -k bvh).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
if ! command -v chromium >/dev/null 2>&1 && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  echo "installing Debian's chromium for the browser test ..."
  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) \
    || echo "could not install chromium: the browser test will be skipped"
fi
# The Khronos glTF validator and three.js from npm, for the glTF and character tests (skipped without
# them): installed once into runs/node_tools (git-ignored) when npm is there.
if command -v npm >/dev/null 2>&1 && [ -z "${HUMOTION_GLTF_VALIDATOR:-}" ]; then
  tools=runs/node_tools
  if [ ! -d "$tools/node_modules/gltf-validator" ] || [ ! -d "$tools/node_modules/three" ]; then
    mkdir -p "$tools"
    (cd "$tools" && npm install --no-audit --no-fund --silent gltf-validator@2.0.0-dev.3.10 three@0.187.0 >/dev/null 2>&1) \
      || echo "could not install gltf-validator and three from npm: the validator and three.js tests will be skipped"
  fi
  export HUMOTION_GLTF_VALIDATOR="$PWD/$tools"
fi
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"   # small tensors: one thread per process is fastest here
exec .venv/bin/python -m pytest -q "$@"
