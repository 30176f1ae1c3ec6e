"""``dynbtf fit-many``: a manifest of BTFs fitted as Ray tasks, against sequential ``dynbtf fit`` runs."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch

from dynbtf.cli.main import main
from dynbtf.data import write_stored
from dynbtf.errors import InputError, MissingDependencyError
from dynbtf.fit_many import read_manifest
from dynbtf.representations.model_file import load_model
from synthetic_btf import synthetic_btf

OPTIONS = ["--epochs", "2", "--texel-groups", "4", "--images-per-step", "8", "--workers", "1"]


@pytest.fixture(scope="module")
def library(tmp_path_factory):
    """Three small stored BTFs and a manifest that fits them (plus one missing file)."""
    root = tmp_path_factory.mktemp("library")
    for k, name in enumerate(("a", "b", "c")):
        btf = synthetic_btf(size=6 + 2 * k, name=name)
        write_stored(root / f"{name}.dbtf", btf, progress=False)
    manifest = root / "library.toml"
    manifest.write_text('[defaults]\nepochs = 2\ntexel_groups = 4\nimages_per_step = 8\n\n'
                        + "".join(f'[[source]]\nbtf = "{n}.dbtf"\n\n' for n in ("a", "b", "c"))
                        + '[[source]]\nbtf = "missing.dbtf"\n')
    return root, manifest


def _tensors(path: Path) -> dict[str, torch.Tensor]:
    rep, _ = load_model(path)
    return rep.state_dict()


def _same_model(a: Path, b: Path) -> None:
    ta, tb = _tensors(a), _tensors(b)
    assert ta.keys() == tb.keys()
    for name in ta:
        assert torch.equal(ta[name], tb[name]), name


@pytest.fixture(scope="module")
def sequential(library, tmp_path_factory):
    """The same three fits as three `dynbtf fit` runs, one after the other, one thread each."""
    root, _ = library
    out = tmp_path_factory.mktemp("sequential")
    for name in ("a", "b", "c"):
        assert main(["fit", str(root / f"{name}.dbtf"), "-o", str(out / f"{name}.dbtfm"), "--quiet", *OPTIONS]) == 0
    return out


def test_fit_many_on_two_workers_gives_the_sequential_models(library, sequential, tmp_path, capsys):
    pytest.importorskip("ray")
    root, manifest = library
    out = tmp_path / "many"
    status = main(["fit-many", str(manifest), "-o", str(out), "--cpus", "2", "--cpus-per-task", "1", "--quiet"])
    printed = capsys.readouterr().out
    assert status == 1  # one source failed
    assert "missing: FAILED: " in printed and "missing.dbtf: not found" in printed and "(3 done, 1 failed)" in printed
    for name in ("a", "b", "c"):
        _same_model(out / f"{name}.dbtfm", sequential / f"{name}.dbtfm")
    rows = json.loads((out / "results.json").read_text())["results"]
    assert [r["name"] for r in rows] == ["a", "b", "c", "missing"]
    assert [r["status"] for r in rows] == ["done", "done", "done", "failed"]
    assert all(r["attempts"] == 1 for r in rows)
    for r in rows[:3]:
        assert 5.0 < r["psnr"] < 80.0 and 0.0 <= r["flip"] <= 1.0 and r["model_bytes"] > 0
    csv_lines = (out / "results.csv").read_text().splitlines()
    assert csv_lines[0].startswith("name,btf,status,psnr") and len(csv_lines) == 5
    html = (out / "index.html").read_text()
    assert all(name in html for name in ("a", "b", "c", "missing"))
    for r in rows[:3]:
        assert r["images"] and all(Path(p).is_file() for p in r["images"])


def test_a_worker_killed_mid_fit_is_retried_and_the_model_is_unchanged(library, sequential, tmp_path):
    ray = pytest.importorskip("ray")
    import fit_many_tasks
    from dynbtf.fit_many import fit_many

    ray.cloudpickle.register_pickle_by_value(fit_many_tasks)  # the workers need not import tests/
    root, manifest = library
    small = tmp_path / "two.toml"
    small.write_text(manifest.read_text().split("[[source]]")[0] + f'[[source]]\nbtf = "{root}/b.dbtf"\n\n'
                     + f'[[source]]\nbtf = "{root}/c.dbtf"\n')
    out = tmp_path / "retried"
    rows = fit_many(small, out, cpus=2, progress=False, task_fn=fit_many_tasks.crash_once_then_fit)
    assert (out / "b.crashed").read_text() == "killed at step 12"  # the first attempt did die
    assert [(r["name"], r["status"], r["attempts"]) for r in rows] == [("b", "done", 2), ("c", "done", 1)]
    for name in ("b", "c"):
        _same_model(out / f"{name}.dbtfm", sequential / f"{name}.dbtfm")


@pytest.mark.parametrize("text, message", [
    ('[defaults]\nepochs = 2\nlearning_rate = 3\n[[source]]\nbtf = "a.dbtf"\n',
     r"m.toml:3: unknown key 'learning_rate' in \[defaults\]"),
    ('[[source]]\nbtf = "a.dbtf"\n\n[[source]]\nname = "b"\nepochs = 2\n',
     r"m.toml:4: \[\[source\]\] #2 has no 'btf' key"),
    ('[[source]]\nbtf = "a.dbtf"\nlr_scale = -1\n', r"m.toml:3: 'lr_scale': --lr-scale .*expected a finite number in \(0, 1000000\], got -1"),
    ('[[source]]\nbtf = "a.dbtf"\nepochs = "many"\n', r"m.toml:3: \[\[source\]\] #1 key 'epochs' = 'many': expected int"),
    ('[[source]]\nbtf = "a.dbtf"\nrepr = "nerf"\n', r"m.toml:3: 'repr': --repr: no fitter for 'nerf'"),
    ('[[source]]\nbtf = "a.dbtf"\n[[source]]\nbtf = "x/a.dbtf"\n', r"m.toml:3: two sources are named 'a'"),
    ('[defaults]\nepochs = 2\n', "no \\[\\[source\\]\\] tables"),
    ('[[source]\nbtf = 1', "not valid TOML"),
    ('[[source]]\nbtf = "m.toml"\n', r"m.toml:2: \[\[source\]\] #1 btf 'm.toml': .*unrecognized format"),  # not a BTF
    ('[[source]]\nbtf = "sim:leather?size=0"\n', r"m.toml:2: .*size: expected an integer number of texels per side"),
    ('[[source]]\nbtf = "sim:leather?size=16&size=8"\n', r"m.toml:2: .*option 'size' is given twice"),
    ('[[source]]\nbtf = "a.dbtf"\ntexels = "66y66"\n', r"m.toml:3: 'texels': expected 'whole', a texel count"),
])
def test_manifest_mistakes_name_the_line_and_key_before_anything_runs(tmp_path, text, message):
    path = tmp_path / "m.toml"
    path.write_text(text)
    with pytest.raises(InputError, match=message):
        read_manifest(path, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_without_ray_the_command_says_how_to_install_it(library, tmp_path, monkeypatch, capsys):
    _, manifest = library
    monkeypatch.setitem(sys.modules, "ray", None)
    assert main(["fit-many", str(manifest), "-o", str(tmp_path / "o")]) == 2
    assert "pip install 'dynbtf[cluster]'" in capsys.readouterr().err
    from dynbtf.fit_many import fit_many

    with pytest.raises(MissingDependencyError):
        fit_many(manifest, tmp_path / "o")
