"""``dynbtf eval`` checks the BTF against the one the model was fitted to (dynbtf.provenance)."""

from __future__ import annotations

import numpy as np
import pytest

from dynbtf.cli.main import main
from dynbtf.data import open_btf
from dynbtf.data.array import ArrayBTF
from dynbtf.data.stored import write_stored
from dynbtf.errors import InputError
from dynbtf.provenance import check_model_source, source_fingerprint
from dynbtf.representations.model_file import load_model, read_model_metadata, save_model
from dynbtf.representations.triple_plane import TriplePlane
from dynbtf.training.fit import training_provenance

from synthetic_btf import synthetic_btf

pytestmark = pytest.mark.usefixtures("single_thread")

COUNTS = (1, 3, 4)  # 8 views x 8 lights


def _store(directory, name: str, source, dtype: str = "float32") -> str:
    path = directory / f"{name}.dbtf"
    write_stored(path, source, dtype=dtype, progress=False)
    return str(path)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A model fitted (`dynbtf fit --repr sh`) to ``fitted.dbtf`` and BTFs that differ from it in one way each."""
    d = tmp_path_factory.mktemp("eval_provenance")
    base = synthetic_btf(8, counts=COUNTS)  # name "synthetic"
    values = np.stack([[base.image(v, l) for l in range(base.n_lights)] for v in range(base.n_views)])
    paths = {
        "fitted": _store(d, "fitted", base),
        "copy": _store(d, "copy", ArrayBTF(values, base.views, base.lights, name="copy of synthetic")),
        "float16": _store(d, "float16", base, dtype="float16"),  # keeps the name, rounds the values
        "changed": _store(d, "changed", ArrayBTF(0.5 * values, base.views, base.lights, name="synthetic")),
        "smaller": _store(d, "smaller", synthetic_btf(6, counts=COUNTS)),
        "fewer_lights": _store(d, "fewer_lights", ArrayBTF(values[:, :-1], base.views, base.lights[:-1],
                                                           name="synthetic")),
        "other_directions": _store(d, "other_directions", synthetic_btf(8, thetas=(0.0, 30.0, 55.0), counts=COUNTS)),
        "other_lights": _store(d, "other_lights", ArrayBTF(values, base.views, base.lights[::-1], name="synthetic")),
    }
    model = d / "sh.dbtfm"
    assert main(["fit", paths["fitted"], "--repr", "sh", "-o", str(model), "--held-out-fraction", "0.1",
                 "--quiet"]) == 0
    pairs = d / "pairs.txt"
    pairs.write_text("0,0\n3,2\n")  # valid in every BTF above
    return {"dir": d, "model": str(model), "pairs": str(pairs), **paths}


def _eval(files, btf, *extra):
    out = files["dir"] / f"eval_{abs(hash((btf, extra)))}"
    return main(["eval", files["model"], btf, "-o", str(out), "--pairs", files["pairs"], "--images", "0",
                 *extra]), out


def test_fit_records_the_source_fingerprint_shared_with_compare(files):
    import dynbtf.compare

    assert dynbtf.compare.source_fingerprint is source_fingerprint  # one implementation
    record = read_model_metadata(files["model"])["provenance"]["source"]
    assert record["fingerprint"] == source_fingerprint(open_btf(files["fitted"]))
    assert record["name"] == "synthetic" and (record["height"], record["width"]) == (8, 8)


def test_eval_on_its_own_btf_is_silent(files, capsys):
    status, out = _eval(files, files["fitted"])
    captured = capsys.readouterr()
    assert status == 0 and "warning" not in captured.err and (out / "metrics.csv").exists()


@pytest.mark.parametrize("which, words", [
    ("smaller", ["'synthetic' (8x8 texels, 8 views x 8 lights)", "'synthetic' (6x6 texels, 8 views x 8 lights)",
                 "different size (height, width)"]),
    ("fewer_lights", ["8 views x 8 lights", "8 views x 7 lights", "different size (n_lights)"]),
    ("other_directions", ["the view and light directions differ", "'synthetic' (8x8 texels, 8 views x 8 lights)"]),
    ("other_lights", ["the light directions differ", "'synthetic' (8x8 texels, 8 views x 8 lights)"]),
])
def test_eval_refuses_a_btf_of_another_size_or_directions(files, capsys, which, words):
    status, out = _eval(files, files[which])
    err = capsys.readouterr().err
    assert status == 2 and not out.exists()
    assert "sh.dbtfm was fitted to" in err and "--force" in err
    for w in words:
        assert w in err


@pytest.mark.parametrize("which, words", [
    ("copy", ["fitted to 'synthetic', evaluated on 'copy of synthetic'", "a copy of that BTF"]),
    ("changed", ["other content of 'synthetic'", "changed since the fit"]),
    ("float16", ["other content of 'synthetic'", "lossy copy"]),
])
def test_eval_warns_about_another_name_or_other_content(files, capsys, which, words):
    status, out = _eval(files, files[which])
    err = capsys.readouterr().err
    assert status == 0 and (out / "metrics.csv").exists()
    assert "dynbtf: warning:" in err
    for w in words:
        assert w in err


@pytest.mark.parametrize("which", ["other_directions", "copy", "changed"])
def test_eval_force_skips_the_check(files, capsys, which):
    status, out = _eval(files, files[which], "--force")
    assert status == 0 and (out / "metrics.csv").exists()
    assert "warning" not in capsys.readouterr().err


def test_eval_force_cannot_make_a_plane_of_another_size_fit(files, capsys):
    status, _ = _eval(files, files["smaller"], "--force")
    assert status == 2 and "positional plane is (8, 8) texels" in capsys.readouterr().err


def test_model_without_a_recorded_source_is_evaluated_with_a_warning(files, tmp_path, capsys):
    model = save_model(tmp_path / "bare.dbtfm", TriplePlane(8, 8, positional_channels=4, angular_channels=2,
                                                            hidden=8))
    assert main(["eval", str(model), files["fitted"], "-o", str(tmp_path / "ev"), "--pairs", files["pairs"],
                 "--images", "0"]) == 0
    assert "records no source BTF" in capsys.readouterr().err


def test_check_model_source_on_simulated_materials_and_older_records():
    leather = open_btf("sim:leather?size=8")
    meta = {"provenance": training_provenance(leather, np.zeros((0, 2), dtype=np.int64))}
    assert check_model_source(meta, leather) == []
    # same grid and size, another material: an error naming both (--force on the command line skips it)
    with pytest.raises(InputError, match=r"m\.dbtfm was fitted to 'sim:leather' .* not to the BTF 'sim:stone' .*"
                                         r"same size and directions but other values"):
        check_model_source(meta, open_btf("sim:stone?size=8"), model="m.dbtfm")
    # another simulation seed: same name, other content
    (warning,) = check_model_source(meta, open_btf("sim:leather?size=8&seed=5"))
    assert "other content of 'sim:leather'" in warning
    with pytest.raises(InputError, match=r"fitted to 'sim:leather' \(8x8 texels.*not to the BTF 'sim:stone' "
                                         r"\(16x16 texels"):
        check_model_source(meta, open_btf("sim:stone?size=16"))
    # model files written before directions and fingerprints were recorded: counts only
    older = {"provenance": {"source": {k: meta["provenance"]["source"][k]
                                       for k in ("name", "height", "width", "n_views", "n_lights")}}}
    assert check_model_source(older, leather) == []
    assert check_model_source(older, open_btf("sim:leather?size=8&seed=5")) == []


def test_fitted_model_loads_and_its_record_matches_the_stored_btf(files):
    rep, meta = load_model(files["model"])
    source = open_btf(files["fitted"])
    assert check_model_source(meta, source) == []
    assert rep.positional_plane().shape[:2] == (source.height, source.width)
