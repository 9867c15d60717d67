#!/usr/bin/env bash
# Create ./.venv and install humotion into it, with torch held to its CPU build
# (constraints.txt), with the test and docs tools. Safe to run again: it only installs what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."
[ -x .venv/bin/python ] || python3 -m venv .venv
.venv/bin/python -m pip install --quiet --disable-pip-version-check -c constraints.txt -e ".[dev,docs]" 2>&1 \
  | grep -v "^WARNING: Location" || true
.venv/bin/python -c "import humotion, torch; print(f'humotion {humotion.__version__} ready (torch {torch.__version__})')"
