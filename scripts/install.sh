#!/usr/bin/env bash
# Install dynbtf and everything it needs on a fresh Debian/Ubuntu machine.
#   bash scripts/install.sh          # the library, its CLI and Mitsuba's LLVM back end
#   bash scripts/install.sh --test   # also the test tools and headless Chromium
# Uses the active Python (a venv if one is active; PYTHON=/path/to/python to choose another).
# A system Python that is "externally managed" (PEP 668: stock Debian 12, Ubuntu 23.04+) refuses
# `pip install` outside a venv: then dynbtf goes into the repository's .venv, created here
# (see scripts/python_env.sh; demo.sh and test.sh run with the same interpreter). Safe to run again.
set -euo pipefail
cd "$(dirname "$0")/.."
. scripts/python_env.sh  # -> PY, DYNBTF_BASE_PYTHON, DYNBTF_VENV

with_test=0
[ "${1:-}" = "--test" ] && with_test=1

venv_ready() {  # the repository's venv exists and has a working pip
  [ -x "$PY" ] && "$PY" -m pip --version >/dev/null 2>&1
}

apt_packages=(libllvm19 g++)  # g++: dynbtf compiles its native training kernel on first use
[ "$with_test" = 1 ] && apt_packages+=(chromium)
if [ -n "$DYNBTF_VENV" ] && ! venv_ready && ! "$DYNBTF_BASE_PYTHON" -c "import ensurepip, venv" 2>/dev/null; then
  # Debian/Ubuntu ship venv's ensurepip separately: python3.X-venv for the interpreter's version
  apt_packages+=("python$("$DYNBTF_BASE_PYTHON" -c 'import sys; print("%d.%d" % sys.version_info[:2])')-venv")
fi

missing=()
for p in "${apt_packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ "${#missing[@]}" -gt 0 ]; then
  echo "== installing system packages: ${missing[*]}"
  SUDO=""
  [ "$(id -u)" = 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${missing[@]}" >/dev/null
fi

if [ -n "$DYNBTF_VENV" ] && ! venv_ready; then
  echo "== $DYNBTF_BASE_PYTHON is externally managed (PEP 668): creating the virtual environment $DYNBTF_VENV"
  "$DYNBTF_BASE_PYTHON" -m venv --clear "$DYNBTF_VENV"
fi

if [ -n "${TORCH_INDEX_URL:-}" ]; then
  # e.g. TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu: PyTorch's CPU-only build (plain PyPI
  # resolves torch to the CUDA build, several GB of NVIDIA libraries a CPU-only machine does not use)
  echo "== installing torch from $TORCH_INDEX_URL"
  "$PY" -m pip install -q --disable-pip-version-check --index-url "$TORCH_INDEX_URL" \
    "$(grep '^torch==' scripts/constraints.txt)"
fi
extra="[render]"  # Mitsuba 3: the demo renders with it
[ "$with_test" = 1 ] && extra="[render,cluster,test]"  # the tests also run fit-many on Ray
echo "== installing dynbtf$extra into $PY (versions pinned by scripts/constraints.txt)"
pip_status=0
"$PY" -m pip install -q --disable-pip-version-check -c scripts/constraints.txt -e ".$extra" 2>&1 \
  | { grep -v "Running pip as the 'root' user" || true; } || pip_status=$?
if [ "$pip_status" != 0 ]; then
  echo "dynbtf: 'pip install -e .$extra' failed (exit status $pip_status) with $PY" >&2
  exit "$pip_status"
fi
"$PY" -c "
import dynbtf, torch, mitsuba
build = 'CPU-only build' if torch.version.cuda is None else f'CUDA {torch.version.cuda} build'
print('dynbtf', dynbtf.__version__, '| torch', torch.__version__, f'({build})', '| mitsuba', mitsuba.__version__)"
