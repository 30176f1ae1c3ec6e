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
# one test process per core (pytest-xdist), each with one thread: most tests are small tensors, Python and
# subprocesses, for which a second OpenMP thread costs more than it gives: the suite takes less than half the time
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
WORKERS="${DYNBTF_TEST_WORKERS:-auto}"
"$PY" -m pytest -q -n "$WORKERS" "$@"
# the AVX2 path (most laptops and desktops), forced where this CPU has more: the tests of the kernels and of the
# numbers they compute (DYNBTF_CPU_ISA=avx2 bash scripts/test.sh runs the whole suite on it)
if [ $# -eq 0 ] && [ -z "${DYNBTF_CPU_ISA:-}" ] && \
   "$PY" -c "import sys, dynbtf.cpu as c; sys.exit(0 if c.ISAS.index(c.hardware_isa()) > c.ISAS.index('avx2') else 1)"; then
  echo "== the AVX2 path (DYNBTF_CPU_ISA=avx2): kernels, training (compiled too), evaluation, one-truth tests"
  DYNBTF_CPU_ISA=avx2 "$PY" -m pytest -q -n "$WORKERS" -p no:cacheprovider tests/test_native_kernel.py tests/test_triple_plane.py \
    tests/test_training.py tests/test_fast_decode.py tests/test_one_truth.py tests/test_parallax_kernels.py \
    tests/test_visible_fetch.py tests/test_cpu_levels.py tests/test_step_loss.py
fi
