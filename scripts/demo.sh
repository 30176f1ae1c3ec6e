#!/usr/bin/env bash
# The main job on the built-in default (a simulated BTF, no download):
# install, then simulate -> fit -> evaluate -> synthesize -> render -> report.html.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
. scripts/python_env.sh  # the interpreter install.sh installed into (the repository's .venv on a PEP 668 system)
# `dynbtf demo` with that interpreter (its help and messages say "dynbtf", as from the installed command)
exec "$PY" -c 'import sys; from dynbtf.cli.main import main; sys.argv[0] = "dynbtf"; sys.exit(main())' demo "$@"
