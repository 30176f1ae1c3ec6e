#!/usr/bin/env bash
# The main job on the built-in default (a simulated BTF, no download):
# install, then simulate -> fit -> evaluate -> synthesize -> render -> report.html.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
exec dynbtf demo "$@"
