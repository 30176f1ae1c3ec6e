"""Shared pytest fixtures.

``DYNBTF_CPU_ISA=avx2 bash scripts/test.sh`` runs the whole suite on the AVX2 path (dynbtf's kernels, PyTorch's,
MKL's and numba's) on a CPU that has more: dynbtf is imported first so that it sets the libraries' variables
before they load (:mod:`dynbtf.cpu`).

``DYNBTF_REQUIRE_BACKENDS=1`` (set by ``.ci/run``) turns a skipped one-truth test (``tests/test_one_truth.py``: a
backend missing -- Mitsuba, Dr.Jit's LLVM, headless Chromium, the native kernel) into a failure: in CI every
backend must be held to the float64 reference, not quietly left out.
"""

import os
import random

import dynbtf  # noqa: F401  (first: DYNBTF_CPU_ISA reaches PyTorch, MKL and numba before they load)
import numpy as np
import pytest
import torch


def pytest_report_header(config):
    from dynbtf.cpu import check_forced_environment, isa_description

    problem = check_forced_environment()
    if problem:
        raise pytest.UsageError(problem)
    return f"dynbtf CPU level: {isa_description()}; PyTorch kernels: {torch.backends.cpu.get_cpu_capability()}"


#: Test modules whose skips are failures under ``DYNBTF_REQUIRE_BACKENDS=1``.
REQUIRED_BACKEND_MODULES = ("test_one_truth",)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if report.skipped and os.environ.get("DYNBTF_REQUIRE_BACKENDS") == "1" and \
            getattr(item.module, "__name__", "").split(".")[-1] in REQUIRED_BACKEND_MODULES:
        reason = report.longrepr[-1] if isinstance(report.longrepr, tuple) else str(report.longrepr)
        report.outcome = "failed"
        report.longrepr = (f"skipped where every backend is required (DYNBTF_REQUIRE_BACKENDS=1): {reason}; "
                           "install what scripts/install.sh --test installs")


@pytest.fixture(autouse=True)
def seeded_random_state():
    """Seed the global torch, numpy and Python generators before every test.

    Tests that draw unseeded random inputs (``torch.rand(...)``) then see the same inputs on every
    run and machine, so a pass or a failure is reproducible rather than a draw.
    """
    torch.manual_seed(1234)
    np.random.seed(1234)
    random.seed(1234)


@pytest.fixture(scope="module")
def single_thread():
    """Run a module's tiny-tensor tests with one torch thread.

    On a loaded 2-core machine torch's 2-thread OpenMP costs up to 50x on tiny tensors.
    Use with ``pytestmark = pytest.mark.usefixtures("single_thread")``.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session", autouse=True)
def small_level_decoder_fit():
    """The per-level decoders' fit at a sixteenth of its default size in tests (4,096 footprints, 300 steps), and the
    top level's mean appearance in a quarter of its steps (500).

    The tests hold the footprint path to references computed with the same fit (the plugin against
    ``SynthesizedBTF.eval``, convergence to brute-force means with tolerances that the small fit meets);
    the default's size buys robustness of the benchmark's FLIP, not correctness, and would double the
    suite's time (a fit per model, method and seed). Subprocesses (CLI tests) use the defaults.
    """
    import dynbtf.material.footprint_decoders as fits

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(fits, "LEVEL_FIT_QUERIES", 4096)
        patch.setattr(fits, "LEVEL_FIT_STEPS", 300)
        patch.setattr(fits, "LEVEL_FIT_BATCH", 1024)
        patch.setattr(fits, "MEAN_FIT_STEPS", 500)
        yield


@pytest.fixture(scope="session", autouse=True)
def private_material_cache(tmp_path_factory):
    """Compiled materials (and the synthesis tables they share between seeds) are cached in a directory of this test
    session, not the user's."""
    import os

    names = {"DYNBTF_COMPILED_CACHE": "compiled-cache"}
    previous = {name: os.environ.get(name) for name in names}
    for name, folder in names.items():
        os.environ[name] = str(tmp_path_factory.mktemp(folder))
    yield
    for name, value in previous.items():
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value


@pytest.fixture(scope="module")
def variant():
    """The Mitsuba variant the plugin tests render with (``llvm_ad_rgb``), the dynbtf plugins registered on it;
    the test is skipped where that variant is not usable."""
    from dynbtf.render.mitsuba.bsdf import plugin_variants, register_plugin

    wanted = "llvm_ad_rgb"
    if wanted not in plugin_variants():  # pragma: no cover - not built, or no LLVM on this machine
        pytest.skip(f"Mitsuba variant {wanted} not usable here")
    register_plugin(wanted)
    return wanted


@pytest.fixture(scope="session")
def small_model(tmp_path_factory):
    """A small Triple Plane model file (16 x 16 texels, 4 positional channels, a decoder of width 8) for command
    line tests: quick to load, render and export."""
    import torch

    from dynbtf.representations.model_file import save_model
    from dynbtf.representations.triple_plane import TriplePlane

    model = TriplePlane(16, 16, positional_channels=4, angular_channels=2, hidden=8, seed=1)
    with torch.no_grad():
        model.decoder.rest[-1].bias.add_(0.5)
    path = tmp_path_factory.mktemp("small-model") / "small.dbtfm"
    save_model(path, model)
    return path
