"""Training: held-out split, convergence on a tiny BTF, resuming, generic representations, evaluation, CLI."""

import json

import numpy as np
import pytest
import torch

from dynbtf.errors import FormatError, InputError
from dynbtf.metrics import dssim, flip, psnr, psnr_fixed_range
from dynbtf.representations.base import Representation
from dynbtf.representations.model_file import load_model
from dynbtf.representations.triple_plane import TriplePlane
from dynbtf.training import ImageStore, TrainConfig, checkpoint_path, fit, held_out_split
from dynbtf.training.evaluate import evaluate_model, resolve_eval_pairs
from dynbtf.training.fitters import fit_triple_plane, get_fitter
from synthetic_btf import synthetic_btf

SMALL = dict(thetas=(0.0, 30.0, 60.0), counts=(1, 6, 8))  # 15 x 15 = 225 pairs


@pytest.fixture(scope="module")
def btf():
    return synthetic_btf(8, **SMALL)


def small_config(**kw):
    base = dict(epochs=2, images_per_step=8, held_out_fraction=0.1, seed=7, checkpoint_every=4, workers=1,
                monitor_pairs=4, device="cpu")
    return TrainConfig(**{**base, **kw})


def test_held_out_split_is_deterministic_disjoint_and_complete():
    train, held = held_out_split(9, 11, 0.05, seed=3)
    train2, held2 = held_out_split(9, 11, 0.05, seed=3)
    assert np.array_equal(held, held2) and np.array_equal(train, train2)
    assert len(held) == round(0.05 * 99) and len(train) + len(held) == 99
    rows = set(map(tuple, train)) | set(map(tuple, held))
    assert rows == {(v, l) for v in range(9) for l in range(11)}
    assert not set(map(tuple, train)) & set(map(tuple, held))
    assert not np.array_equal(held_out_split(9, 11, 0.05, seed=4)[1], held)
    assert len(held_out_split(9, 11, 0.0, seed=3)[1]) == 0
    with pytest.raises(InputError, match="held_out_fraction"):
        held_out_split(9, 11, 1.0, seed=3)


def test_image_store_cache_and_streaming_agree(btf):
    cached, streamed = ImageStore(btf), ImageStore(btf, memory_budget=0)
    assert cached.cached and not streamed.cached
    pairs = np.array([[0, 3], [14, 2]])
    texels = np.array([1, 9, 63])
    exact = np.stack([btf.image(v, l).reshape(-1, 3) for v, l in pairs])
    np.testing.assert_array_equal(streamed.get(pairs), exact)
    np.testing.assert_allclose(cached.get(pairs), exact, rtol=1e-3)  # float16 cache
    np.testing.assert_allclose(cached.get(pairs, texels), exact[:, texels], rtol=1e-3)


@pytest.mark.parametrize("gather", ["native", "numpy"])
@pytest.mark.parametrize("budget", [2 ** 30, 0])
def test_image_store_blocks_match_scattered_reads(btf, budget, gather, monkeypatch):
    """get_blocks(pairs (G, B, 2), starts, n) == get(pairs[g], texels of block g) side by side, wrapping at the end
    (the cache's native gather and its NumPy fallback; get converts with NumPy)."""
    from dynbtf.training import images

    if gather == "numpy":
        monkeypatch.setattr(images, "_native_gather", lambda: None)
    elif images._native_gather() is None:
        pytest.skip("no native kernel on this machine")
    store = ImageStore(btf, memory_budget=budget)
    pairs = np.array([[[0, 3], [14, 2]], [[5, 5], [1, 0]], [[2, 9], [2, 9]]])
    store.fill(pairs.reshape(-1, 2))  # cached: both read the float16 cache
    starts = np.array([0, 58, 20])  # the second block wraps: texels 58..63, 0..3
    blocks = store.get_blocks(pairs, starts, 10)
    assert blocks.shape == (2, 30, 3) and blocks.dtype == np.float32
    for g in range(3):
        texels = (starts[g] + np.arange(10)) % 64
        np.testing.assert_array_equal(blocks[:, 10 * g:10 * (g + 1)], store.get(pairs[g], texels))
    with pytest.raises(InputError, match="length"):
        store.get_blocks(pairs, starts, 65)
    with pytest.raises(InputError, match="pairs"):
        store.get_blocks(pairs[0], starts, 4)


def test_training_a_tiny_btf_reduces_held_out_error(tmp_path, btf):
    _, held = held_out_split(btf.n_views, btf.n_lights, 0.1, seed=7)
    initial = TriplePlane(8, 8, seed=7)
    before = evaluate_model(initial, btf, held, progress=False).mean
    result = fit_triple_plane(btf, tmp_path / "m.dbtfm", small_config(epochs=25, lr_scale=10.0),
                              progress=False)
    after = evaluate_model(result.representation, btf, held, progress=False).mean
    assert result.finished and result.history[-1]["epoch"] == 25
    assert before["psnr"] < 10 and after["psnr"] > 26, (before, after)
    assert after["flip"] < 0.5 * before["flip"] and after["dssim"] < before["dssim"]
    meta = result.metadata["provenance"]
    assert np.array_equal(np.asarray(meta["held_out_pairs"]), held)
    assert meta["source"]["n_views"] == 15 and meta["seed"] == 7 and meta["epochs_completed"] == 25
    assert meta["size"]["model_bytes"] == result.representation.storage_bytes()


def test_held_out_pairs_are_never_trained_on(tmp_path, btf, monkeypatch):
    requested = []
    original = ImageStore.get

    def spy(self, pairs, texels=None, **options):
        requested.extend(map(tuple, np.asarray(pairs)))
        return original(self, pairs, texels, **options)

    monkeypatch.setattr(ImageStore, "get", spy)
    fit_triple_plane(btf, tmp_path / "m.dbtfm", small_config(epochs=2, monitor_pairs=0), progress=False)
    train, held = held_out_split(btf.n_views, btf.n_lights, 0.1, seed=7)
    assert set(requested) == set(map(tuple, train))  # every training pair, nothing else
    assert len(requested) == 2 * len(train)


class Interrupt(Exception):
    pass


@pytest.mark.parametrize("stop_after", [5, 13])  # mid-epoch, and at the start of epoch 2
def test_resume_continues_where_it_stopped(tmp_path, btf, stop_after):
    config = small_config(epochs=2, workers=2, chunk_texels=16)
    reference = fit_triple_plane(btf, tmp_path / "ref.dbtfm", config, progress=False).representation
    steps = []

    def stop(info):
        steps.append(info["global_step"])
        if info["global_step"] == stop_after:
            raise Interrupt

    out = tmp_path / "resumed.dbtfm"
    with pytest.raises(Interrupt):
        fit(TriplePlane(8, 8, seed=7), btf, config, out, progress=False, callback=stop)
    assert checkpoint_path(out).exists() and not out.exists()
    state = torch.load(checkpoint_path(out), weights_only=True)
    steps_per_epoch = int(np.ceil(len(held_out_split(15, 15, 0.1, 7)[0]) / 8))
    assert state["epoch"] * steps_per_epoch + state["step"] == stop_after
    resumed_steps = []
    result = fit(TriplePlane(8, 8, seed=99 - 92), btf, config, out, progress=False,
                 callback=lambda info: resumed_steps.append(info["global_step"]))
    assert resumed_steps[0] == stop_after + 1 and resumed_steps[-1] == 2 * steps_per_epoch
    for (name, a), b in zip(reference.state_dict().items(), result.representation.state_dict().values()):
        assert torch.equal(a, b), name
    # a finished run re-run does nothing more and gives the same model
    again = fit(TriplePlane(8, 8, seed=7), btf, config, out, progress=False,
                callback=lambda info: pytest.fail("trained again"))
    assert all(torch.equal(a, b) for a, b in zip(reference.parameters(), again.representation.parameters()))


def test_checkpoint_of_another_run_or_damaged_is_refused(tmp_path, btf):
    out = tmp_path / "m.dbtfm"
    fit_triple_plane(btf, out, small_config(epochs=1), progress=False)
    with pytest.raises(InputError, match="different training run.*seed"):
        fit_triple_plane(btf, out, small_config(epochs=1, seed=8), progress=False)
    checkpoint_path(out).write_bytes(b"garbage")
    with pytest.raises(FormatError, match="damaged checkpoint"):
        fit_triple_plane(btf, out, small_config(epochs=1), progress=False)


def test_time_budget_stops_early_and_a_rerun_finishes(tmp_path, btf):
    out = tmp_path / "m.dbtfm"
    partial = fit_triple_plane(btf, out, small_config(epochs=3, max_minutes=1e-6), progress=False)
    assert not partial.finished and partial.metadata["provenance"]["epochs_completed"] < 3
    done = fit_triple_plane(btf, out, small_config(epochs=3), progress=False)
    assert done.finished and done.metadata["provenance"]["epochs_completed"] == 3


def test_texel_subsets_train_streamed_without_cache(tmp_path, btf, monkeypatch):
    """The large-BTF path: no image cache (every step decodes), random texel subsets."""
    monkeypatch.setattr(ImageStore, "fill", lambda *a, **k: pytest.fail("a streamed run must not pre-decode"))
    result = fit_triple_plane(btf, tmp_path / "m.dbtfm", small_config(epochs=3, texels_per_image=20,
                                                                      memory_budget_mb=0.01), progress=False)
    assert result.metadata["provenance"]["samples_per_epoch"] == 20 * 203
    assert np.isfinite(result.history[-1]["held_out_psnr"])


def test_texel_groups_cover_every_pair_per_pass_and_resume(tmp_path, btf, monkeypatch):
    """texel_groups=G: each step has G x B pairs on disjoint blocks of consecutive texels covering the image;
    an epoch visits every pair G times."""
    calls = []
    original = ImageStore.get_blocks

    def spy(self, pairs, starts, length, **options):
        calls.append((np.asarray(pairs).copy(), np.asarray(starts).copy(), length))
        return original(self, pairs, starts, length, **options)

    monkeypatch.setattr(ImageStore, "get_blocks", spy)
    config = small_config(epochs=2, texel_groups=4, images_per_step=8, monitor_pairs=0)
    result = fit_triple_plane(btf, tmp_path / "g.dbtfm", config, progress=False)
    train, _ = held_out_split(btf.n_views, btf.n_lights, 0.1, seed=7)
    steps_per_epoch = int(np.ceil(len(train) / 8))
    assert len(calls) == 2 * steps_per_epoch  # one store read per step
    for pairs, starts, length in calls:
        assert pairs.shape == (4, 8, 2) and length == 16
        texels = (starts[:, None] + np.arange(16)[None]) % 64
        assert np.array_equal(np.sort(texels.ravel()), np.arange(64))  # disjoint groups covering the image
    assert len({int(starts[0]) for _, starts, _ in calls}) > 1  # the blocks move from step to step
    first_epoch = np.concatenate([p.reshape(-1, 2) for p, _, _ in calls[:steps_per_epoch]])
    counts = {}
    for pair in map(tuple, first_epoch):
        counts[pair] = counts.get(pair, 0) + 1
    assert set(counts) == set(map(tuple, train))
    assert min(counts.values()) >= 4 and sum(counts.values()) == 4 * 8 * steps_per_epoch  # G passes (+ wrap-around)
    # resuming a grouped run mid-epoch ends with the same parameters
    monkeypatch.setattr(ImageStore, "get_blocks", original)

    def stop(info):
        if info["global_step"] == 7:
            raise Interrupt

    out = tmp_path / "resumed.dbtfm"
    with pytest.raises(Interrupt):
        fit(TriplePlane(8, 8, seed=7), btf, config, out, progress=False, callback=stop)
    resumed = fit(TriplePlane(8, 8, seed=7), btf, config, out, progress=False).representation
    for (name, a), b in zip(result.representation.state_dict().items(), resumed.state_dict().values()):
        assert torch.equal(a, b), name
    with pytest.raises(InputError, match="texel_groups"):
        fit_triple_plane(btf, tmp_path / "x.dbtfm", small_config(texel_groups=40), progress=False)


class PerTexelColour(Representation):
    """A minimal representation without fast paths: RGB plane, directions ignored."""

    kind = "test-per-texel"

    def __init__(self, height, width):
        super().__init__()
        self.plane = torch.nn.Parameter(torch.zeros(height, width, 3))

    def positional_plane(self):
        return self.plane

    def decode(self, features, w_view, w_light):
        return features

    def config(self):
        return {"height": self.plane.shape[0], "width": self.plane.shape[1]}


def test_any_representation_with_parameters_trains(tmp_path, btf):
    rep = PerTexelColour(8, 8)
    config = small_config(epochs=8, lr_scale=30.0)
    result = fit(rep, btf, config, tmp_path / "m.dbtfm", progress=False)
    # the best direction-independent colour under L1 is the per-texel median over the training pairs
    train, _ = held_out_split(btf.n_views, btf.n_lights, 0.1, seed=7)
    median = np.median([btf.image(v, l) for v, l in train], axis=0)
    plane = result.representation.plane.detach().numpy()
    assert np.abs(plane - median).mean() < 0.05 < 0.1 * np.abs(median).mean() * 2


def test_evaluation_matches_metrics_and_writes_outputs(tmp_path, btf):
    rep = TriplePlane(8, 8, seed=1)
    pairs = np.array([[0, 1], [3, 4], [14, 14]])
    ev = evaluate_model(rep, btf, pairs, out_dir=tmp_path / "ev", images=2, progress=False)
    uv = torch.from_numpy(np.stack(np.meshgrid((np.arange(8) + .5) / 8, (np.arange(8) + .5) / 8), -1))
    for row, (v, l) in zip(ev.rows, pairs):
        wv = torch.as_tensor(btf.views[v], dtype=torch.float32).expand(8, 8, 3)
        wl = torch.as_tensor(btf.lights[l], dtype=torch.float32).expand(8, 8, 3)
        img = rep(uv, wv, wl).detach().numpy()
        gt = btf.image(v, l)
        assert row["psnr"] == pytest.approx(psnr(gt, img), abs=1e-3)
        assert row["dssim"] == pytest.approx(dssim(gt, img), abs=1e-4)
        assert row["flip"] == pytest.approx(flip(gt, img), abs=1e-4)
        assert row["psnr_fixed1"] == pytest.approx(psnr_fixed_range(gt, img), abs=1e-3)
        theta_view, theta_light = np.degrees(np.arccos(btf.views[v][2])), np.degrees(np.arccos(btf.lights[l][2]))
        assert row["grazing"] == (max(theta_view, theta_light) > 60 + 1e-6)
    table = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    assert table["n_pairs"] == 3 and table["mean"]["psnr"] == pytest.approx(np.mean([r["psnr"] for r in ev.rows]))
    assert "per-image peak" in table["metrics"]["psnr"] and "fixed peak 1" in table["metrics"]["psnr_fixed1"]
    for name in ("grazing", "others"):
        group = [r for r in ev.rows if r["grazing"] == (name == "grazing")]
        assert table["by_angle"][name]["n"] == len(group)
        if group:
            assert table["by_angle"][name]["psnr"] == pytest.approx(np.mean([r["psnr"] for r in group]))
    csv_lines = (tmp_path / "ev" / "metrics.csv").read_text().splitlines()
    n_groups = sum(1 for g in table["by_angle"].values() if g["n"])
    assert len(csv_lines) == 5 + n_groups and csv_lines[4].startswith("mean")
    assert "per-image peak" in ev.summary() and "fixed peak 1" in ev.summary()
    assert sorted(p.name for p in (tmp_path / "ev").glob("*.png")) == ["pair_v000_l001.png", "pair_v014_l014.png"]


def test_evaluation_splits_grazing_pairs_from_the_others():
    """Grazing: view or light beyond 60 degrees (the ring at exactly 60 is not); means per group by hand."""
    btf = synthetic_btf(8, thetas=(0.0, 60.0, 75.0), counts=(1, 4, 4))  # 9 directions
    rep = TriplePlane(8, 8, seed=2)
    pairs = np.array([[0, 0], [1, 2], [5, 0], [0, 6], [8, 8], [2, 3]])
    ev = evaluate_model(rep, btf, pairs, progress=False)
    theta = lambda w: np.degrees(np.arccos(np.clip(w[2], -1, 1)))  # noqa: E731
    expected = [max(theta(btf.views[v]), theta(btf.lights[l])) > 60.001 for v, l in pairs]
    assert [r["grazing"] for r in ev.rows] == expected == [False, False, True, True, True, False]
    for name, flag in (("grazing", True), ("others", False)):
        group = [r for r, e in zip(ev.rows, expected) if e == flag]
        assert ev.by_angle[name]["n"] == 3
        for metric in ("psnr", "psnr_fixed1", "dssim", "flip"):
            assert ev.by_angle[name][metric] == pytest.approx(np.mean([r[metric] for r in group]))


def test_eval_pair_lists(tmp_path, btf):
    meta = {"provenance": {"held_out_pairs": [[1, 2]]}}
    assert resolve_eval_pairs("held-out", btf, meta).tolist() == [[1, 2]]
    assert len(resolve_eval_pairs("all", btf, meta)) == 225
    listing = tmp_path / "pairs.csv"
    listing.write_text("view,light\n3, 4\n# comment\n5 6\n")
    assert resolve_eval_pairs(str(listing), btf).tolist() == [[3, 4], [5, 6]]
    listing.write_text("3,4\n99,0\n")
    with pytest.raises(InputError, match=r"\(99, 0\) is outside"):
        resolve_eval_pairs(str(listing), btf)
    with pytest.raises(InputError, match="no held-out"):
        resolve_eval_pairs("held-out", btf, {})
    with pytest.raises(InputError, match="--repr"):
        get_fitter("no-such-kind")


def test_cli_fit_eval_inspect(tmp_path, btf, monkeypatch, capsys):
    from dynbtf.cli import model_commands
    from dynbtf.cli.main import main

    monkeypatch.setattr(model_commands, "_open_source", lambda spec: btf)
    model = tmp_path / "m.dbtfm"
    assert main(["fit", "tiny", "-o", str(model), "--epochs", "1", "--quiet", "--workers", "1",
                 "--device", "cpu", "--texel-groups", "2"]) == 0
    assert "wrote" in capsys.readouterr().out
    assert main(["eval", str(model), "tiny", "-o", str(tmp_path / "ev"), "--images", "1"]) == 0
    assert "PSNR" in capsys.readouterr().out and (tmp_path / "ev" / "metrics.csv").exists()
    assert main(["inspect", str(model), "-o", str(tmp_path / "planes")]) == 0
    out = capsys.readouterr().out
    assert "triple" in out and "compression" in out and (tmp_path / "planes" / "positional_pca.png").exists()
    assert load_model(model)[1]["provenance"]["epochs_completed"] == 1
    assert load_model(model)[1]["provenance"]["training"]["texel_groups"] == 2
    (tmp_path / "bad.dbtfm").write_bytes(b"\x00" * 20)
    assert main(["inspect", str(tmp_path / "bad.dbtfm")]) == 2
    assert "bad.dbtfm" in capsys.readouterr().err


def test_a_finished_fit_leaves_no_checkpoint_and_is_not_overwritten_by_another_run(tmp_path, btf, capsys):
    out = tmp_path / "m.dbtfm"
    fit(TriplePlane(8, 8, seed=7), btf, small_config(epochs=1), out, progress=False)
    assert out.exists() and not checkpoint_path(out).exists()
    before = out.read_bytes()
    again = fit(TriplePlane(8, 8, seed=7), btf, small_config(epochs=1), out, progress=True)
    assert "already a finished fit with these options" in capsys.readouterr().out
    assert again.finished and out.read_bytes() == before
    with pytest.raises(InputError, match=r"holds a fit of a different training run \(differs in \['lr_scale'\]\)"):
        fit(TriplePlane(8, 8, seed=7), btf, small_config(epochs=1, lr_scale=2.0), out, progress=False)
    assert out.read_bytes() == before
