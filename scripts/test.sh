#!/usr/bin/env bash
# Install dynbtf with its test tools (and headless Chromium), check the import layers, then run the test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh --test
# third-party cross-check of our UBO2014 reader (tests skip if this build fails)
bash scripts/install_btf_extractor.sh || echo "btf-extractor could not be installed: its cross-check tests will skip"
. scripts/python_env.sh  # the interpreter install.sh installed into (the repository's .venv on a PEP 668 system)
# the pipeline's layers point one way (contract in pyproject.toml, [tool.importlinter])
echo "== import layers (import-linter)"
"$PY" -c "import sys; from importlinter.cli import lint_imports_command; sys.argv[0] = 'lint-imports'; sys.exit(lint_imports_command())" \
  --no-cache
exec "$PY" -m pytest -q "$@"
