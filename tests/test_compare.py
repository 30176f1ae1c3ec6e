"""``dynbtf.compare``: one held-out split for all representations, tables, figure, reuse of model files."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from dynbtf.compare import compare_representations, example_images, fit_or_load
from dynbtf.errors import InputError
from dynbtf.metrics import flip, psnr
from dynbtf.training import TrainConfig, held_out_split

from test_baselines import analytic_btf


pytestmark = pytest.mark.usefixtures("single_thread")


@pytest.fixture(scope="module")
def btf():
    return analytic_btf(12, 12, seed=1)


CONFIG = TrainConfig(epochs=2, held_out_fraction=0.1, seed=2, device="cpu", workers=1)


def test_compare_writes_tables_and_figure_on_the_same_held_out_pairs(btf, tmp_path):
    scores = compare_representations(btf, tmp_path, ["pca", "sh", "neumip"], CONFIG, examples=2, progress=False)
    assert [s.kind for s in scores] == ["pca", "sh", "neumip"]
    _, held = held_out_split(btf.n_views, btf.n_lights, 0.1, 2)
    for s in scores:
        assert [(r["view_index"], r["light_index"]) for r in s.per_pair] == [tuple(p) for p in held.tolist()]
        assert s.storage_bytes >= s.positional_bytes > 0 and s.finished
    # the table's numbers are the means of independent per-pair recomputations
    pca = scores[0]
    rep, _ = fit_or_load("pca", btf, tmp_path / "pca.dbtfm", CONFIG, progress=False)
    images = example_images(rep, btf, held)
    truths = [btf.image(int(v), int(l)) for v, l in held]
    assert pca.flip == pytest.approx(np.mean([flip(t, img) for t, (img, _, _) in zip(truths, images)]), rel=1e-6)
    assert pca.psnr == pytest.approx(np.mean([psnr(t, img) for t, (img, _, _) in zip(truths, images)]), rel=1e-6)
    with open(tmp_path / "representations.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["kind"] for r in rows] == ["pca", "sh", "neumip"]
    assert float(rows[1]["flip"]) == pytest.approx(scores[1].flip)
    data = json.loads((tmp_path / "representations.json").read_text())
    assert data["held_out_pairs"] == held.tolist() and set(data["per_pair"]) == {"pca", "sh", "neumip"}
    html = (tmp_path / "index.html").read_text()
    assert "representations.png" in html and "<table" in html
    import imageio.v3 as iio

    figure = iio.imread(tmp_path / "representations.png")
    assert figure.ndim == 3 and figure.shape[1] > figure.shape[0]  # 2 rows x 7 columns (GT, 3 reps, 3 maps)


def test_compare_reuses_models_and_refuses_foreign_ones(btf, tmp_path):
    compare_representations(btf, tmp_path, ["pca"], CONFIG, examples=1, progress=False)
    before = (tmp_path / "pca.dbtfm").stat().st_mtime_ns
    compare_representations(btf, tmp_path, ["pca"], CONFIG, examples=1, progress=False)
    assert (tmp_path / "pca.dbtfm").stat().st_mtime_ns == before  # loaded, not refitted
    other = TrainConfig(epochs=2, held_out_fraction=0.1, seed=3, device="cpu", workers=1)
    with pytest.raises(InputError, match="held-out pairs differ"):
        compare_representations(btf, tmp_path, ["pca"], other, examples=1, progress=False)
    changed = analytic_btf(12, 12, seed=9)  # same name and shape, other content
    with pytest.raises(InputError, match="fitted to different content"):
        compare_representations(changed, tmp_path, ["pca"], CONFIG, examples=1, progress=False)
    with pytest.raises(InputError, match="no fitter for 'nope'"):
        compare_representations(btf, tmp_path, ["nope"], CONFIG, progress=False)


def test_compare_command_line(btf, tmp_path, capsys):
    from dynbtf.cli.main import main
    from dynbtf.data.stored import write_stored

    path = tmp_path / "small.dbtf"
    write_stored(path, btf, dtype="float32", progress=False)
    out = tmp_path / "out"
    assert main(["compare", str(path), "-o", str(out), "--repr", "pca,sh", "--examples", "1",
                 "--held-out-fraction", "0.1", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "pca" in printed and "sh" in printed and (out / "index.html").exists()
    assert (out / "pca.dbtfm").exists() and (out / "eval_sh" / "metrics.csv").exists()
    assert main(["compare", str(path), "-o", str(out), "--repr", "pca,bogus"]) == 2
    assert "no fitter for 'bogus'" in capsys.readouterr().err
    # the same baselines through `dynbtf fit --repr` and `dynbtf eval`
    assert main(["fit", str(path), "--repr", "sh", "-o", str(tmp_path / "sh.dbtfm"), "--held-out-fraction", "0.1",
                 "--quiet"]) == 0
    assert main(["eval", str(tmp_path / "sh.dbtfm"), str(path), "-o", str(tmp_path / "eval"), "--images", "1"]) == 0
    assert "FLIP" in capsys.readouterr().out and (tmp_path / "eval" / "metrics.csv").exists()


def test_compare_passes_training_options_and_refuses_models_trained_otherwise(btf, tmp_path, capsys):
    from dynbtf.cli.main import main
    from dynbtf.data.stored import write_stored
    from dynbtf.representations.model_file import read_model_metadata

    path = tmp_path / "small.dbtf"
    write_stored(path, btf, dtype="float32", progress=False)
    out = tmp_path / "out"

    def args(epochs=1, lr_scale="3"):
        return ["compare", str(path), "-o", str(out), "--repr", "neumip", "--examples", "1", "--held-out-fraction",
                "0.1", "--epochs", str(epochs), "--workers", "1", "--device", "cpu", "--quiet", "--lr-scale", lr_scale,
                "--texel-groups", "2", "--images-per-step", "4", "--precision", "fp32"]

    assert main(args()) == 0
    training = read_model_metadata(out / "neumip.dbtfm")["provenance"]["training"]
    assert (training["lr_scale"], training["texel_groups"], training["images_per_step"], training["precision"],
            training["epochs"]) == (3.0, 2, 4, "fp32", 1)
    before = (out / "neumip.dbtfm").stat().st_mtime_ns
    capsys.readouterr()
    assert main(args()) == 0  # same options: loaded, not refitted
    assert (out / "neumip.dbtfm").stat().st_mtime_ns == before
    capsys.readouterr()
    # other options (the paper's learning rates; more epochs): refused, not silently reused or overwritten
    assert main(args(lr_scale="1")) == 2
    assert "lr_scale=3.0 (this comparison: 1.0)" in capsys.readouterr().err
    assert main(args(epochs=2)) == 2
    assert "epochs=1 (this comparison: 2)" in capsys.readouterr().err
    assert (out / "neumip.dbtfm").stat().st_mtime_ns == before


def test_compare_synthesis_reports_quality_and_quilting_storage(btf, tmp_path):
    from dynbtf.compare import compare_synthesis
    from dynbtf.representations.pca import fit_pca

    model = fit_pca(btf, components=2, progress=False)
    rows = compare_synthesis(model, tmp_path, ["tile", "quilt"], scale=3, seed=1, resolution=24, progress=False)
    by = {r["method"]: r for r in rows}
    plane = model.positional_plane()
    assert by["tile"]["synthesis_storage_bytes"] == 0 and by["tile"]["repetition"] > 0.9
    assert by["tile"]["dynamic"] and not by["quilt"]["dynamic"]
    # quilting stores its pre-generated plane: (at least) 3 x 3 exemplars of the plane's channels, float32
    assert by["quilt"]["synthesis_storage_bytes"] >= 9 * plane.numel() * 4 * 0.9
    assert all(r["total_bytes"] == r["representation_bytes"] + r["synthesis_storage_bytes"] for r in rows)
    assert (tmp_path / "synthesis.csv").exists() and (tmp_path / "images" / "synthesis_quilt.png").exists()
    with pytest.raises(InputError, match="scale"):
        compare_synthesis(model, tmp_path, ["tile"], scale=1)
