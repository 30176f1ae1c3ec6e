"""Per-element variation of structured synthesis (dynbtf.synthesis.elements and struct's brightness and tint):
the element grid against a wall whose bricks are known, the element instances against exact rational arithmetic,
the factors' statistics, and the query, plugin-facing and command-line behaviour."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
import torch

from dynbtf.errors import InputError
from dynbtf.synthesis.cell_quilting import CellQuilting
from dynbtf.synthesis.elements import VARIATION_SALT, element_gain, element_grid, element_instances

H = W = 64
BRICK_W, BRICK_H, JOINT = 16, 8, 2


def _wall(seed: int = 1):
    """A running bond (16 x 8-texel bricks, half bond, 2-texel joints) of distinct brick colours on dark mortar:
    ``(plane (H, W, 3) float32, brick (course, column) of each texel, joint mask)``."""
    y, x = np.mgrid[0:H, 0:W]
    course = y // BRICK_H
    shifted = x + (BRICK_W // 2) * (course % 2)
    joint = (shifted % BRICK_W < JOINT) | (y % BRICK_H < JOINT)
    colour = np.random.default_rng(seed).uniform(0.3, 1.0, (H // BRICK_H, W // BRICK_W, 3))
    plane = np.where(joint[..., None], 0.05, colour[course, (shifted // BRICK_W) % (W // BRICK_W)])
    return torch.from_numpy(plane.astype(np.float32)), (course, shifted // BRICK_W), joint


def test_the_grid_of_a_running_bond_is_its_bricks_and_joints():
    plane, _, joint = _wall()
    grid = CellQuilting(plane, seed=0, fast=False).prepared.element_grid.tolist()
    columns, rows, p, q, phase_x, phase_y = grid
    assert (columns, rows, p, q) == (W // BRICK_W, H // BRICK_H, 1, 2)
    # the borders lie in the joints: the placement is within the 2-texel joints, modulo an element
    assert (phase_x % BRICK_W) in (0.0, 0.5, 1.0, 1.5, 2.0) and (phase_y % BRICK_H) in (0.0, 0.5, 1.0, 1.5, 2.0)
    joints = CellQuilting(plane, seed=0, fast=False).prepared.joints.numpy().astype(bool)
    assert (joints == joint).mean() > 0.97


@pytest.mark.parametrize("grid", [[4, 8, 1, 2, 0.5, 1.0], [3, 6, 1, 3, 2.25, 0.0], [5, 4, 0, 1, 0.0, 3.5],
                                  [2, 7, 3, 4, 1.0, 1.0]])
def test_element_instances_are_exact_far_from_the_origin(grid):
    """Against exact rational arithmetic: row = floor((Y - phase_y) / c), column = floor((X - phase_x) / a - row p/q)
    for X = (iu + fu) W, Y = (iv + fv) H, with repeat indices up to 2**32 (fractions of 20 bits: uv exact)."""
    rng = np.random.default_rng(3)
    whole = rng.integers(-2 ** 32, 2 ** 32, size=(300, 2)).astype(np.float64)
    whole[:40] = rng.integers(-3, 3, size=(40, 2))
    frac = np.floor(rng.random((300, 2)) * 2 ** 20) / 2 ** 20  # exact dyadic fractions: the sum is exact in float64
    points = torch.from_numpy(whole + frac)
    assert (points.numpy() - whole == frac).all()
    column, row = element_instances(points, grid, H, W)
    columns, rows, p, q = (int(v) for v in grid[:4])
    a, c = Fraction(W, columns), Fraction(H, rows)
    for k in range(300):
        x = (int(whole[k, 0]) + Fraction(frac[k, 0])) * W
        y = (int(whole[k, 1]) + Fraction(frac[k, 1])) * H
        r = (y - Fraction(grid[5])) // c
        col = (x - Fraction(grid[4])) / a - r * Fraction(p, q)
        assert int(row[k]) == r and int(column[k]) == col // 1


def test_one_factor_per_brick_with_the_asked_spread_and_none_on_joints():
    plane, _, joint = _wall()
    synth = CellQuilting(plane, seed=5, fast=False, brightness=0.2, tint=0.1)
    side = 24 * W  # 24 x 24 repeats far from the origin: about 18,000 bricks
    y, x = np.mgrid[0:side, 0:side].reshape(2, -1) + 0.5
    points = torch.from_numpy(np.stack([1e9 + x / W, 3e9 + y / H], -1))
    gain = synth.variation_gain(points).numpy()
    course = np.floor(y / BRICK_H).astype(np.int64)
    column = np.floor((x + (BRICK_W // 2) * (course % 2)) / BRICK_W).astype(np.int64)
    on_joint = joint[(y.astype(np.int64)) % H, (x.astype(np.int64)) % W]
    assert (gain[on_joint] == 1.0).all()
    key = course * 10 ** 6 + column
    inside = ~on_joint
    # one factor per brick: every texel of a brick has its brick's factor
    _, first = np.unique(key[inside], return_index=True)
    per_brick = dict(zip(key[inside][first], map(tuple, gain[inside][first])))
    assert all(per_brick[k] == tuple(g) for k, g in zip(key[inside][::97], gain[inside][::97]))
    logs = np.log(np.array(list(per_brick.values()), dtype=np.float64))
    assert len(logs) > 15000
    brightness, tint = logs.mean(1), logs - logs.mean(1, keepdims=True)
    assert brightness.std() == pytest.approx(0.2, rel=0.05) and abs(brightness.mean()) < 0.01
    assert tint.std(0) == pytest.approx([0.1 * np.sqrt(2 / 3)] * 3, rel=0.05)
    # another seed, other factors; off: none
    other = CellQuilting(plane, seed=6, fast=False, brightness=0.2, tint=0.1).variation_gain(points[:5000]).numpy()
    assert np.abs(other - gain[:5000]).max() > 0.1
    assert CellQuilting(plane, seed=5, fast=False).variation_gain(points) is None


def test_wide_footprints_average_the_factors_towards_one():
    plane, _, _ = _wall()
    synth = CellQuilting(plane, seed=5, fast=False, brightness=0.3)
    points = torch.from_numpy(np.random.default_rng(0).random((4000, 2)) * 50 + 1e6)
    point = np.log(synth.variation_gain(points).numpy())
    one_texel = np.log(synth.variation_gain(points, torch.full((4000,), 1.0, dtype=torch.float64)).numpy())
    wide = np.log(synth.variation_gain(points, torch.full((4000,), 4 * np.sqrt(BRICK_W * BRICK_H),
                                                           dtype=torch.float64)).numpy())
    assert np.array_equal(one_texel, point)
    assert np.allclose(wide, point / 4, atol=1e-6)


def test_eval_multiplies_the_decoded_reflectance_by_the_factors():
    from dynbtf.representations.triple_plane import TriplePlane
    from dynbtf.synthesized import synthesized_btf

    model = TriplePlane(H, W, seed=2)
    with torch.no_grad():
        model.f_u.copy_(_wall()[0].repeat(1, 1, 6)[..., :model.f_u.shape[-1]] - 0.5)
    rng = np.random.default_rng(1)
    uv = rng.random((3000, 2)) * 30 + 1e7
    wv = np.tile([0.0, 0.0, 1.0], (3000, 1))
    wl = np.tile([0.6, 0.0, 0.8], (3000, 1))
    plain = synthesized_btf(model, "struct", seed=3)
    varied = synthesized_btf(model, "struct", seed=3, brightness=0.2, tint=0.2)
    gain = varied.synthesizer.variation_gain(torch.from_numpy(uv)).numpy()
    assert np.array_equal(varied.eval(uv, wv, wl), plain.eval(uv, wv, wl) * gain)
    assert not np.allclose(gain, 1.0)


def test_bad_variation_and_tables_without_elements_are_one_line_errors():
    plane, _, _ = _wall()
    for value in (-0.1, 1.5, float("nan"), "a", True):
        with pytest.raises(InputError, match="brightness: expected the standard deviation of a log gain"):
            CellQuilting(plane, fast=False, brightness=value)
    old = CellQuilting(plane, fast=False).prepared
    old.element_grid = old.joints = None  # tables of a material compiled before the element grid
    with pytest.raises(InputError, match="no element map"):
        CellQuilting(plane, fast=False, tint=0.1, prepared=old)
    assert CellQuilting(plane, fast=False, prepared=old).variation_gain(torch.zeros(3, 2, dtype=torch.float64)) is None


def test_the_web_form_carries_the_variation_it_draws():
    """With brightness or tint, the web form adds the joints table and the element grid, strengths and hash state."""
    from dynbtf.synthesis.cell_quilting.web import form
    from dynbtf.synthesis.hash import seed_state

    plane, _, _ = _wall()
    plain = form(CellQuilting(plane, fast=False))
    assert "elements" not in plain.constants and "joints" not in plain.tables["tables"].values
    varied = CellQuilting(plane, fast=False, brightness=0.25, tint=0.125, seed=9)
    f = form(varied)
    t = varied.prepared
    np.testing.assert_array_equal(f.tables["tables"].values["joints"], t.joints.numpy().astype(np.int16))
    e = f.constants["elements"]
    assert e["grid"] == t.element_grid.tolist() and (e["brightness"], e["tint"]) == (0.25, 0.125)
    columns, rows, p, q = (int(v) for v in e["grid"][:4])
    assert (e["columns"], e["rows"], e["shift"]) == (columns, rows, rows * p // q) and (rows * p) % q == 0
    assert e["state"] == int(seed_state(9 ^ VARIATION_SALT))


def test_element_gain_on_a_grid_without_elements_is_one_row_per_repeat():
    """An exemplar without structure: one element per repeat (the grid of :func:`element_grid` with no offsets)."""
    grid, joints = element_grid(np.zeros((1, 2), dtype=np.int64), np.random.default_rng(0).random((16, 16, 2)))
    assert grid[:4].tolist() == [1, 1, 0, 1]
    # one element per repeat, from the grid's placement on: points in one repeat of it share their factor
    start = np.array([5.0 + grid[4] / 16, 7.0 + grid[5] / 16])
    points = torch.from_numpy(np.stack([start + 0.1, start + [0.9, 0.6], start + [1.1, 0.2]]))
    g = element_gain(points, grid.tolist(), torch.zeros(16, 16, dtype=torch.int8), 0, 0.3, 0.0)
    assert torch.equal(g[0], g[1]) and not torch.equal(g[0], g[2])


def test_synth_draws_the_variation_and_refuses_it_where_it_does_not_apply(tmp_path, monkeypatch, capsys):
    from dynbtf.cli.main import main
    from dynbtf.io import load_image
    from dynbtf.representations.model_file import save_model
    from dynbtf.representations.triple_plane import TriplePlane

    monkeypatch.setenv("DYNBTF_COMPILED_CACHE", "off")
    model = TriplePlane(H, W, seed=2)
    with torch.no_grad():
        model.f_u.copy_(_wall()[0].repeat(1, 1, 6)[..., :model.f_u.shape[-1]] - 0.5)
    save_model(tmp_path / "wall.dbtfm", model)
    common = [str(tmp_path / "wall.dbtfm"), "--method", "struct", "--scale", "4", "--resolution", "64"]
    assert main(["synth", *common, "-o", str(tmp_path / "plain.exr")]) == 0
    assert main(["synth", *common, "--brightness", "0.3", "--tint", "0.2", "-o", str(tmp_path / "varied.exr")]) == 0
    plain, varied = load_image(tmp_path / "plain.exr"), load_image(tmp_path / "varied.exr")
    ratio = varied / np.maximum(plain, 1e-6)
    assert np.isfinite(varied).all() and np.abs(np.log(ratio[plain > 1e-3])).max() > 0.1
    capsys.readouterr()
    for extra, message in ((["--method", "hist", "--brightness", "0.1"], "--brightness: per-element variation is "
                                                                          "struct's; give it with --method struct"),
                           (["--method", "struct", "--tint", "1.5"], "--tint: expected the standard deviation of a "
                                                                     "log gain in [0, 1]")):
        assert main(["synth", str(tmp_path / "wall.dbtfm"), *extra, "-o", str(tmp_path / "x.png")]) == 2
        assert message in capsys.readouterr().err
        assert not (tmp_path / "x.png").exists()
    # export draws it for struct (the viewer's shader: tests/test_web_export.py), and refuses it where no exported
    # method takes it
    import json

    assert main(["export", str(tmp_path / "wall.dbtfm"), "-o", str(tmp_path / "web"), "--method", "struct",
                 "--method", "hist", "--brightness", "0.3", "--tint", "0.2", "--no-viewer"]) == 0
    methods = json.loads((tmp_path / "web" / "manifest.json").read_text())["methods"]
    assert (methods["struct"]["elements"]["brightness"], methods["struct"]["elements"]["tint"]) == (0.3, 0.2)
    assert "elements" not in methods["hist"]
    capsys.readouterr()
    for extra, message in ((["--brightness", "0.1"], "--brightness: per-element variation is for struct; export it "
                                                     "with --method (without --layer or --target), not ['auto', "
                                                     "'hist', 'tile']"),
                           (["--method", "struct", "--tint", "2"], "--tint: expected the standard deviation")):
        assert main(["export", str(tmp_path / "wall.dbtfm"), *extra, "-o", str(tmp_path / "x")]) == 2
        assert message in capsys.readouterr().err
        assert not (tmp_path / "x").exists()
