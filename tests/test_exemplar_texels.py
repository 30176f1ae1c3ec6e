"""Fitting a BTF at another texel count (dynbtf.data.resampled, dynbtf.training.exemplar_texels, ``fit --texels``):
the resample against a closed-form periodic signal, the whole-element size of brick walls whose bricks are known,
and the command line's fit, record and eval."""

from __future__ import annotations

import numpy as np
import pytest

from dynbtf.cli.main import main
from dynbtf.data.array import ArrayBTF
from dynbtf.data.resampled import ResampledBTF
from dynbtf.data.stored import write_stored
from dynbtf.errors import InputError
from dynbtf.provenance import source_as_fitted
from dynbtf.representations.model_file import read_model_metadata
from dynbtf.synthesis.cell_quilting import elements_of
from dynbtf.synthesis.elements import element_grid, whole_element_size
from dynbtf.training.exemplar_texels import parse_texels, resample_for_fit, whole_element_texels

LIGHTS = [[0.0, 0.0, 1.0], [0.5, 0.0, np.sqrt(0.75)]]


def _signal(u, v, light):
    """A periodic, band-limited, positive reflectance over the repeat (two cycles at most along each axis)."""
    return (1.0 + 0.4 * np.sin(2 * np.pi * (u + 2 * v) + light) + 0.3 * np.cos(2 * np.pi * 2 * u)
            + 0.2 * np.sin(2 * np.pi * v)) * np.array([1.0, 0.8, 0.6])


def _sampled(height: int, width: int) -> ArrayBTF:
    """:func:`_signal` at the texel centres of ``height x width`` texels, one view, two lights."""
    y, x = np.mgrid[0:height, 0:width] + 0.5
    values = np.stack([_signal((x / width)[..., None], (y / height)[..., None], l) for l in range(2)])[None]
    return ArrayBTF(values.astype(np.float32), [[0.0, 0.0, 1.0]], LIGHTS, name="waves")


def test_the_resample_is_the_periodic_signal_at_the_new_texel_centres():
    coarse = _sampled(40, 48)
    fine = ResampledBTF(coarse, 52, 60)
    assert fine.shape == (1, 2, 52, 60) and fine.name == "waves (resampled to 52 x 60 texels)"
    y, x = np.mgrid[0:52, 0:60] + 0.5
    for light in range(2):
        exact = _signal((x / 60)[..., None], (y / 52)[..., None], light)
        got = fine.image(0, light)
        # a cubic spline through 20+ samples per cycle: error ~ (2 pi / 20)^4 / 384 of the amplitude
        assert np.abs(got - exact).max() < 2e-4, np.abs(got - exact).max()
        flat = np.array([5, 17, 52 * 60 - 1])
        assert np.array_equal(fine.read_texels([[0, light]], flat)[0], got.reshape(-1, 3)[flat])
    # the same size returns the source's values; a resample keeps the repeat (its mean)
    assert np.array_equal(ResampledBTF(coarse, 40, 48).image(0, 1), coarse.image(0, 1))
    assert abs(fine.image(0, 0).mean() - coarse.image(0, 0).mean()) < 1e-3


def test_ringing_next_to_a_sharp_edge_never_goes_below_zero():
    step = np.zeros((1, 1, 16, 16, 3), dtype=np.float32)
    step[..., 4:12, :] = 1.0
    out = ResampledBTF(ArrayBTF(step, [[0, 0, 1.0]], [[0, 0, 1.0]]), 16, 21).image(0, 0)
    assert out.min() == 0.0 and out.max() > 1.0  # the spline overshoots above, is held at 0 below


@pytest.mark.parametrize("height, width, words", [(0, 8, "height: expected a positive integer number of texels"),
                                                  (8, 2.5, "width: expected a positive integer"),
                                                  (8, True, "width: expected a positive integer"),
                                                  (8, 100, "width: 100 texels is more than 4x away from the "
                                                   "source's 16")])
def test_bad_texel_counts_are_named(height, width, words):
    source = ArrayBTF(np.ones((1, 1, 16, 16, 3), dtype=np.float32), [[0, 0, 1.0]], [[0, 0, 1.0]])
    with pytest.raises(InputError, match=words):
        ResampledBTF(source, height, width)


def _bond(columns: int, rows: int, size: int = 64, seed: int = 0):
    """A running bond (half bond) of ``columns x rows`` bricks per repeat over ``size x size`` texels, measured at
    the texel centres (bricks ``size / columns`` wide: whole texels or not), each brick its own colour, mortar
    joints 1.5 texels wide; the ``(1, 2)`` BTF of it under two lights."""
    y, x = np.mgrid[0:size, 0:size] + 0.5
    a, c = size / columns, size / rows
    course = np.floor(y / c).astype(int)
    along = x / a + 0.5 * (course % 2)
    column = np.floor(along).astype(int)
    head = np.minimum(along - column, column + 1 - along) * a  # texels to the nearest head joint
    bed = np.minimum(y / c - course, course + 1 - y / c) * c  # and bed joint
    joint = (head < 0.75) | (bed < 0.75)
    colour = np.random.default_rng(seed).uniform(0.3, 1.0, (rows, columns, 3))[course % rows, column % columns]
    plane = np.where(joint[..., None], 0.08, colour)
    values = np.stack([plane, 0.7 * plane])[None].astype(np.float32)
    return ArrayBTF(values, [[0.0, 0.0, 1.0]], LIGHTS, name=f"bond {columns}x{rows}")


def test_a_half_bond_whose_period_is_not_whole_texels_is_read_as_a_half_bond():
    """The lattice offsets of a 3 x 6 half bond over 64 texels are rounded to whole texels (a row step of 11 for
    10.67, a brick of 21 for 21.33); the row shift is still a half, and the whole size 66 x 66."""
    offsets = np.array([[0, 0], [32, 32], [32, 11], [32, 53], [21, 0], [43, 0], [11, 32], [53, 32], [0, 21],
                        [0, 43], [53, 11], [11, 53], [43, 21], [21, 43], [21, 21], [43, 43]])
    look = _bond(3, 6).image(0, 0).astype(np.float64)
    grid, _ = element_grid(offsets, look)
    assert grid[:4].tolist() == [3, 6, 1, 2]
    assert whole_element_size(grid, 64, 64) == (66, 66)


@pytest.mark.parametrize("columns, rows, size, expected", [(3, 6, 64, (66, 66)), (4, 8, 64, (64, 64)),
                                                             (5, 6, 64, (66, 60))])
def test_whole_element_texels_of_brick_walls(columns, rows, size, expected):
    """The size at which the bricks are whole: each row whole texels high, each brick an even number wide (the
    half bond's shift then is whole too), nearest the BTF's own."""
    wall = _bond(columns, rows, size)
    grid, strength = elements_of(wall.image(0, 0))
    assert strength > 0.5 and grid[:4].tolist() == [columns, rows, 1, 2]
    (h, w), sentence = whole_element_texels(wall)
    assert (h, w) == expected and h % rows == 0 and (w // columns) % 2 == 0
    assert f"{columns} x {rows} elements per repeat" in sentence and "rows shifted 1/2" in sentence
    assert ("kept at 64 x 64" in sentence) == (expected == (64, 64))
    resampled, said = resample_for_fit(wall, "whole")
    assert (resampled.height, resampled.width) == expected and said == sentence


def test_a_btf_without_elements_keeps_its_size():
    noise = np.random.default_rng(4).uniform(0.2, 0.8, (1, 1, 48, 48, 3)).astype(np.float32)
    source = ArrayBTF(noise, [[0, 0, 1.0]], [[0, 0, 1.0]], name="noise")
    same, sentence = resample_for_fit(source, "whole")
    assert same is source and "no element lattice in noise" in sentence and "kept at 48 x 48" in sentence


@pytest.mark.parametrize("text, expected", [("66x64", (66, 64)), ("66X64", (66, 64)), ("48", (48, 48)),
                                            ("whole", "whole"), (" Whole ", "whole")])
def test_parse_texels(text, expected):
    assert parse_texels(text) == expected


@pytest.mark.parametrize("text", ["", "0", "66x", "x66", "66x64x2", "-4", "2.5", "all"])
def test_bad_texels_are_one_line_errors(text):
    with pytest.raises(InputError, match=r"--texels: expected 'whole', a texel count N \(N x N\) or HxW"):
        parse_texels(text)


def test_fit_with_texels_whole_records_it_and_eval_resamples_the_same_way(tmp_path, capsys):
    btf = tmp_path / "wall.dbtf"
    write_stored(btf, _bond(3, 6), dtype="float32", progress=False)
    model = tmp_path / "wall.dbtfm"
    assert main(["fit", str(btf), "--repr", "sh", "--texels", "whole", "-o", str(model), "--held-out-fraction",
                 "0.5"]) == 0
    out = capsys.readouterr().out
    assert "--texels whole: 3 x 6 elements per repeat (21.33 x 10.67 texels, rows shifted 1/2 of an element): " \
           "resampled from 64 x 64 to 66 x 66 texels (22 x 11 each)" in out
    record = read_model_metadata(model)["provenance"]["source"]
    assert (record["height"], record["width"], record["resampled_from"]) == (66, 66, [64, 64])
    assert record["name"] == "bond 3x6 (resampled to 66 x 66 texels)"
    # eval on the BTF as given: resampled as the fit did, then checked (same name, size and content: silent)
    status = main(["eval", str(model), str(btf), "-o", str(tmp_path / "eval"), "--images", "0"])
    captured = capsys.readouterr()
    assert status == 0 and "warning" not in captured.err, captured.err
    assert (tmp_path / "eval" / "metrics.csv").exists()
    # a BTF of another size is not resampled: the check refuses it as before
    meta = read_model_metadata(model)
    other = ArrayBTF(np.ones((1, 2, 32, 32, 3), dtype=np.float32), [[0.0, 0.0, 1.0]], LIGHTS)
    assert source_as_fitted(meta, other) is other


def test_fit_refuses_bad_texels_before_opening_the_btf(tmp_path, capsys):
    assert main(["fit", str(tmp_path / "missing.btf"), "--texels", "66y66", "-o", str(tmp_path / "m.dbtfm")]) != 0
    err = capsys.readouterr().err
    assert "--texels: expected 'whole'" in err and "Traceback" not in err


def test_a_fit_many_task_with_texels_fits_the_resampled_btf(tmp_path):
    from dynbtf.fit_many import FitTask, fit_one

    btf = tmp_path / "wall.dbtf"
    write_stored(btf, _bond(3, 6), dtype="float32", progress=False)
    task = FitTask(name="wall", btf=str(btf), options={"repr": "sh", "texels": "whole", "held_out_fraction": 0.5},
                   output_dir=str(tmp_path / "out"))
    row = fit_one(task)
    assert row["status"] == "done", row.get("error")
    record = read_model_metadata(task.model_path)["provenance"]["source"]
    assert (record["height"], record["width"], record["resampled_from"]) == (66, 66, [64, 64])


def test_struct_advises_whole_texels_only_where_its_elements_are_not():
    import torch

    from dynbtf.synthesis.cell_quilting import CellQuilting

    def plane(btf):
        return torch.from_numpy(np.asarray(btf.image(0, 0)))

    third = CellQuilting(plane(_bond(3, 6)), seed=0, fast=False).advice()
    assert len(third) == 1 and "the elements are 21.33 x 10.67 texels, not whole texels" in third[0]
    assert "--texels whole` (66 x 66 texels)" in third[0]
    assert CellQuilting(plane(_bond(4, 8)), seed=0, fast=False).advice() == []
    assert CellQuilting(plane(ResampledBTF(_bond(3, 6), 66, 66)), seed=0, fast=False).advice() == []
