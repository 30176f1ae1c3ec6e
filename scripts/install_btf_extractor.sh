#!/usr/bin/env bash
# Optional: install btf-extractor 1.7.0 (the third-party UBO2014/UBO2003 reader) into its own venv,
# so tests/test_data_ubo2014.py::test_against_btf_extractor can cross-check our DFMF reader and writer.
#   bash scripts/install_btf_extractor.sh            # creates .venv-btfx in the repository
#   DYNBTF_BTFX_VENV=/some/dir bash scripts/install_btf_extractor.sh
# btf-extractor's build pins numpy < 1.20 (no wheels for Python 3.11), so it is built without build
# isolation against numpy < 2 and Cython < 3. Takes ~30 s; safe to run again (does nothing when ready).
# The test finds the venv at .venv-btfx, or via DYNBTF_BTFX_PYTHON=/path/to/python.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV="${DYNBTF_BTFX_VENV:-.venv-btfx}"
PY="${PYTHON:-python3}"
if [ -x "$VENV/bin/python" ] && "$VENV/bin/python" -c "import btf_extractor" 2>/dev/null; then
  echo "btf-extractor already installed in $VENV"
  exit 0
fi
"$PY" -m venv "$VENV"
"$VENV/bin/python" -m pip install -q --disable-pip-version-check "numpy<2" "Cython<3" poetry-core
"$VENV/bin/python" -m pip install -q --disable-pip-version-check --no-build-isolation "btf-extractor==1.7.0"
"$VENV/bin/python" -c "import btf_extractor; print('btf-extractor ready in $VENV')"
