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
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"   # small tensors: one thread per process is fastest here
exec .venv/bin/python -m pytest -q "$@"
