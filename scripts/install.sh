#!/usr/bin/env bash
# Install dynbtf and everything it needs on a fresh Debian/Ubuntu machine.
#   bash scripts/install.sh          # the library, its CLI and Mitsuba's LLVM back end
#   bash scripts/install.sh --test   # also the test tools and headless Chromium
# Uses the active Python (a venv if one is active). Safe to run again.
set -euo pipefail
cd "$(dirname "$0")/.."

with_test=0
[ "${1:-}" = "--test" ] && with_test=1

apt_packages=(libllvm19 g++)  # g++: dynbtf compiles its native training kernel on first use
[ "$with_test" = 1 ] && apt_packages+=(chromium)

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

PY="${PYTHON:-python3}"
extra=""
[ "$with_test" = 1 ] && extra="[test]"
echo "== installing dynbtf$extra (torch 2.13.0 CPU build pinned)"
"$PY" -m pip install -q --disable-pip-version-check -e ".$extra" 2>&1 | grep -v "Running pip as the 'root' user" || true
"$PY" -c "import dynbtf, torch, mitsuba; print('dynbtf', dynbtf.__version__, '| torch', torch.__version__, '| mitsuba', mitsuba.__version__)"
