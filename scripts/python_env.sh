# Sourced (from the repository root) by install.sh, demo.sh and test.sh: the one Python they all use.
#
#   PYTHON (default python3), as now, when it runs in a virtual environment or is not
#   "externally managed";
#   otherwise -- a system Python marked EXTERNALLY-MANAGED (PEP 668: stock Debian 12,
#   Ubuntu 23.04+), where `pip install` outside a venv is refused -- the repository's
#   virtual environment .venv (created from PYTHON by scripts/install.sh).
#
# Sets DYNBTF_BASE_PYTHON (the interpreter asked for), DYNBTF_VENV (the venv directory,
# empty when none is needed) and PY (the interpreter to install into and run with).
# The choice is the same test as pip's own: the marker file in the stdlib directory,
# and the interpreter not running in a virtual environment.

DYNBTF_BASE_PYTHON="${PYTHON:-python3}"
if ! _dynbtf_state="$("$DYNBTF_BASE_PYTHON" -c '
import os, sys, sysconfig
in_venv = sys.prefix != sys.base_prefix
marker = os.path.join(sysconfig.get_path("stdlib"), "EXTERNALLY-MANAGED")
print("managed" if os.path.isfile(marker) and not in_venv else "ok")
')"; then
  echo "dynbtf: cannot run the Python interpreter '$DYNBTF_BASE_PYTHON' (install Python >= 3.11, or set PYTHON=/path/to/python)" >&2
  exit 1
fi
if [ "$_dynbtf_state" = managed ]; then
  DYNBTF_VENV="$PWD/.venv"
  PY="$DYNBTF_VENV/bin/python"
else
  DYNBTF_VENV=""
  PY="$DYNBTF_BASE_PYTHON"
fi
unset _dynbtf_state
