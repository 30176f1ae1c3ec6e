#!/usr/bin/env bash
# Install dynbtf with its test tools (and headless Chromium), then run the test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh --test
PY="${PYTHON:-python3}"
exec "$PY" -m pytest -q "$@"
