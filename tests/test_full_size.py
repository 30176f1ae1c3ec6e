"""Full-size BTFs: training streamed from a DFMF file, the auto recipe, resuming, memory errors, the demo's fit.

The full-size data path is exercised on small files that are forced out of the image cache
(``memory_budget_mb`` below the BTF's float16 size): the same code runs at 400 x 400.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from dynbtf.cli.main import app
from dynbtf.data import UBO2014BTF, write_ubo2014
from dynbtf.errors import InputError
from dynbtf.representations.model_file import load_model
from dynbtf.representations.triple_plane import TriplePlane
from dynbtf.training import ImageStore, TrainConfig, checkpoint_path, fit
from dynbtf.training import recipe as recipe_module
from dynbtf.training.checkpoint import Checkpointer
from dynbtf.training.recipe import auto_recipe
from interrupt import Stop, stop_at
from synthetic_btf import synthetic_btf


@pytest.fixture(scope="module")
def dfmf(tmp_path_factory):
    """A 12 x 12 texel, 15 x 15 direction DFMF file (half factors, 12 components)."""
    src = synthetic_btf(12, thetas=(0.0, 30.0, 60.0), counts=(1, 6, 8))
    return write_ubo2014(tmp_path_factory.mktemp("dfmf") / "m.btf", src, components=12, scalar="half")


def streamed(**kw):
    """Options whose cache budget is below the BTF (225 pairs x 144 texels x 6 bytes = 0.19 MB): streamed."""
    base = dict(epochs=2, images_per_step=8, held_out_fraction=0.1, seed=5, workers=1, monitor_pairs=4,
                device="cpu", memory_budget_mb=0.1, texel_groups=4, lr_scale=3.0, checkpoint_every=3)
    return TrainConfig(**{**base, **kw})


def test_streamed_fit_reads_texels_from_the_factors_and_matches_the_cached_fit(tmp_path, dfmf, monkeypatch):
    with UBO2014BTF(dfmf) as btf:
        assert not ImageStore(btf, int(0.1 * 1024 ** 2)).cached
        reads = []
        original = UBO2014BTF._read_texels
        monkeypatch.setattr(UBO2014BTF, "_read_texels", lambda self, *a: reads.append(a[1].shape) or original(self, *a))
        images = []
        decode = UBO2014BTF._read_image
        monkeypatch.setattr(UBO2014BTF, "_read_image", lambda self, v, l: images.append((v, l)) or decode(self, v, l))
        losses = {"streamed": [], "cached": []}
        fit(TriplePlane(12, 12, seed=5), btf, streamed(monitor_pairs=0), tmp_path / "s.dbtfm", progress=False,
            callback=lambda info: losses["streamed"].append(info["loss"]))
        assert reads and all(shape == (4, 36) for shape in reads)  # 4 groups of 144 / 4 texels per step
        assert images == [(0, 0), (14, 14)]  # whole images: only the model file's content fingerprint
        monkeypatch.undo()
        fit(TriplePlane(12, 12, seed=5), btf, streamed(monitor_pairs=0, memory_budget_mb=64), tmp_path / "c.dbtfm",
            progress=False, callback=lambda info: losses["cached"].append(info["loss"]))
    # the same batches, targets equal up to the cache's float16: the first steps' losses agree
    np.testing.assert_allclose(losses["streamed"][:3], losses["cached"][:3], rtol=1e-3)


@pytest.mark.parametrize("stop_after", [4, 11])
def test_interrupted_streamed_fit_resumes_to_the_same_model(tmp_path, dfmf, stop_after):
    with UBO2014BTF(dfmf) as btf:
        reference = fit(TriplePlane(12, 12, seed=5), btf, streamed(), tmp_path / "ref.dbtfm", progress=False)

        out = tmp_path / "run.dbtfm"
        with pytest.raises(Stop):
            fit(TriplePlane(12, 12, seed=5), btf, streamed(), out, progress=False, callback=stop_at(stop_after))
        assert checkpoint_path(out).exists() and not out.exists()
        resumed = fit(TriplePlane(12, 12, seed=5), btf, streamed(), out, progress=False)
    for (name, a), b in zip(reference.representation.state_dict().items(), resumed.representation.state_dict().values()):
        assert torch.equal(a, b), name


def test_memory_budget_too_small_for_one_step_names_the_minimum(tmp_path, dfmf):
    with UBO2014BTF(dfmf) as btf:
        with pytest.raises(InputError, match=r"--memory-mb 0\.001 is too small .* at least 1 MB"):
            fit(TriplePlane(12, 12), btf, streamed(memory_budget_mb=0.001), tmp_path / "m.dbtfm", progress=False)
    assert not (tmp_path / "m.dbtfm").exists() and not checkpoint_path(tmp_path / "m.dbtfm").exists()


def test_recipe_keeps_the_reference_schedule_per_texel():
    """30 epochs on the UBO2003 grid (81 x 81), 9 on UBO2014's (151 x 151): the same ~11,700 steps; total decay 0.9^30."""
    class Grid:  # only the sizes matter to the recipe without a time budget
        def __init__(self, n, size):
            self.n_views = self.n_lights = n
            self.height = self.width = size
            self.n_pairs = n * n

    small = auto_recipe(Grid(81, 128))
    big = auto_recipe(Grid(151, 400))
    assert (small.config.epochs, big.config.epochs) == (30, 9)
    for r in (small, big):
        assert r.config.texel_groups == 64 and r.config.lr_scale == 6.0 and r.config.texels_per_image is None
        assert r.config.lr_decay ** r.config.epochs == pytest.approx(0.9 ** 30)
    assert "(9 epochs x 1354 at most)" in big.summary and "texels read from the BTF" in big.summary
    assert (small.config.schedule, big.config.schedule) == ("converge", "converge")  # the epochs are the ceiling
    huge = auto_recipe(Grid(151, 1024))
    assert huge.config.texels_per_image == 1 << 18 and "262144 texels per step" in huge.summary
    few = auto_recipe(Grid(5, 16))  # 24 training pairs: one group of 16
    assert few.config.texel_groups == 1
    assert auto_recipe(Grid(151, 400), epochs=3, texel_groups=8).config.texel_groups == 8  # overrides win
    with pytest.raises(InputError, match="--minutes"):
        auto_recipe(Grid(81, 128), minutes=0)


def test_recipe_shortens_the_schedule_to_fit_a_time_budget(monkeypatch):
    class Grid:
        n_views = n_lights = 81
        height = width = 128
        n_pairs = 81 * 81

    monkeypatch.setattr(recipe_module, "measure_step_seconds", lambda *a, **k: 0.1)  # 390 steps/epoch: 39 s each
    r = auto_recipe(Grid(), minutes=6)  # 0.9 * 360 s / 39 s = 8 epochs
    assert r.config.epochs == 8 and r.config.max_minutes == 6
    assert r.config.lr_decay ** 8 == pytest.approx(0.9 ** 30)
    assert "the budget allows 8 of 30 epochs" in r.summary
    assert auto_recipe(Grid(), minutes=600).config.epochs == 30  # never more than the full schedule


def test_measured_step_time_is_positive_and_real():
    src = synthetic_btf(8, thetas=(0.0, 30.0, 60.0), counts=(1, 6, 8))
    config = TrainConfig(texel_groups=2, workers=1, device="cpu")
    assert 0 < recipe_module.measure_step_seconds(src, config, steps=2) < 5


@pytest.mark.parametrize("step_seconds, warm, timed", [(0.001, 40, 40), (0.02, 13, 25), (0.3, 2, 5)])
def test_step_timing_warms_up_then_times_at_least_its_seconds(monkeypatch, step_seconds, warm, timed):
    """measure_step_seconds on a fake clock where every step takes ``step_seconds``: at least two warm-up steps and
    WARM_UP_SECONDS of them, then at least ``steps`` steps and TIMED_SECONDS of them, each phase at most
    MAX_TIMED_STEPS; the median (x 1.05 for the update) is what it returns."""
    import torch

    clock = {"now": 0.0, "steps": 0}

    def fake_loss(*args, **kwargs):
        clock["now"] += step_seconds
        clock["steps"] += 1
        return torch.zeros((), requires_grad=True)

    monkeypatch.setattr(recipe_module.StepLoss, "batch", fake_loss)
    monkeypatch.setattr(recipe_module.time, "perf_counter", lambda: clock["now"])
    src = synthetic_btf(8, thetas=(0.0, 30.0, 60.0), counts=(1, 6, 8))
    seconds = recipe_module.measure_step_seconds(src, TrainConfig(texel_groups=2, workers=1, device="cpu"), steps=5)
    assert clock["steps"] == warm + timed
    assert seconds == pytest.approx(step_seconds * 1.05)


def test_cli_fit_states_the_recipe_and_a_rerun_continues_with_it(tmp_path, dfmf, monkeypatch):
    import importlib
    import itertools
    import types

    fit_module = importlib.import_module("dynbtf.training.fit")  # the module (dynbtf.training.fit is also a function)

    out = tmp_path / "m.dbtfm"
    runner = CliRunner()
    # the fit's clock advances 10 s per reading (the command's start read from it too): the 0.06 s budget runs out
    # after the first step, on any machine
    import dynbtf.cli.app as cli_app

    clock = itertools.count(0.0, 10.0)
    monkeypatch.setattr(fit_module, "time", types.SimpleNamespace(perf_counter=lambda: next(clock)))
    monkeypatch.setattr(cli_app, "command_started", lambda: next(clock))
    first = runner.invoke(app, ["fit", str(dfmf), "-o", str(out), "--repr", "triple", "--max-minutes", "0.001",
                                "--epochs", "2",
                                "--device", "cpu", "--workers", "1"])
    monkeypatch.undo()
    assert first.exit_code == 0, first.output
    assert "recipe for 12 x 12 texels, 15 x 15 directions: 2 epochs" in first.output
    saved = Checkpointer.saved_config(checkpoint_path(out))
    assert saved["epochs"] == 2 and saved["texel_groups"] == 13  # 213 training pairs // 16
    second = runner.invoke(app, ["fit", str(dfmf), "-o", str(out), "--repr", "triple", "--device", "cpu",
                                 "--workers", "1"])
    assert second.exit_code == 0, second.output
    assert "continuing" in second.output and "(2 epochs)" in second.output
    meta = load_model(out)[1]["provenance"]
    assert meta["finished"] and meta["epochs_completed"] == 2
    bad = runner.invoke(app, ["fit", str(dfmf), "-o", str(tmp_path / "x.dbtfm"), "--recipe", "fast"])
    assert isinstance(bad.exception, InputError) and "--recipe 'fast'" in str(bad.exception)


def test_rerunning_a_finished_auto_fit_keeps_its_options_whatever_the_machine_measures(tmp_path, dfmf, capsys,
                                                                                      monkeypatch):
    """`dynbtf fit --minutes M` times steps to choose its schedule; a rerun of the finished fit must not
    re-time and refuse its own model file as "another run"."""
    from dynbtf.cli.main import main
    from dynbtf.training import recipe

    out = tmp_path / "m.dbtfm"
    monkeypatch.setattr(recipe, "measure_step_seconds", lambda *a, **k: 1.0)  # the budget allows one epoch
    assert main(["fit", str(dfmf), "-o", str(out), "--minutes", "0.5", "--quiet"]) == 0
    before = out.read_bytes()
    monkeypatch.setattr(recipe, "measure_step_seconds", lambda *a, **k: 1e-4)  # now it would allow all epochs
    assert main(["fit", str(dfmf), "-o", str(out), "--minutes", "0.5"]) == 0
    printed = capsys.readouterr().out
    assert "is a finished fit" in printed and "already a finished fit with these options" in printed
    assert out.read_bytes() == before


def test_the_paper_recipe_is_the_papers():
    """--recipe paper: 16 whole images per step, the paper's learning rates and decay, 50 epochs."""
    from dynbtf.data.open import open_btf
    from dynbtf.training.recipe import choose_config

    config, summary = choose_config(open_btf("sim:leather?size=8"), "unused.dbtfm", recipe="paper")
    assert (config.epochs, config.images_per_step, config.texel_groups, config.lr_scale, config.lr_decay) == \
        (50, 16, 1, 1.0, 0.9)
    assert summary.startswith("the paper's recipe: 50 epochs")
    config, _ = choose_config(open_btf("sim:leather?size=8"), "unused.dbtfm", recipe="paper", epochs=3, minutes=2.0)
    assert config.epochs == 3 and config.max_minutes == 2.0
