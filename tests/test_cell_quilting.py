"""Lattice-aligned cell quilting (``struct``), the structure analysis and ``auto``: against independent references."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from dynbtf.errors import InputError
from dynbtf.synthesis import cell_quilting, make_synthesizer
from dynbtf.synthesis.auto import choose_method
from dynbtf.synthesis.cell_quilting import CROSSING_WEIGHT, SPREAD_WEIGHT, CellQuilting, build_cell_tables
from dynbtf.synthesis.elements import broken_elements
from dynbtf.synthesis.hash import hash_vertex
from dynbtf.synthesis.structure import STRUCTURE_THRESHOLD, analyze_structure, autocorrelation


def _lattice_exemplar(period=8, repeats=4, channels=4, variation=0.1, seed=0):
    """A structured plane: one element repeated on a square lattice, plus per-element random tints."""
    rng = np.random.default_rng(seed)
    element = rng.random((period, period, channels))
    plane = np.tile(element, (repeats, repeats, 1))
    tints = rng.normal(size=(repeats, repeats, channels)) * variation
    plane += np.repeat(np.repeat(tints, period, 0), period, 1)
    return torch.from_numpy(plane.astype(np.float32))


def _brute_force_read(synth: CellQuilting, u: float, v: float) -> tuple[int, tuple[float, float]]:
    """The offset index and read texel position of one query, in Python integers and floats (no numpy/torch)."""
    t = synth.prepared
    h, w = synth.exemplar.shape[:2]
    nx, ny = t.cells
    tx, ty = w // nx, h // ny
    mx, my = t.margin
    k = t.count
    iu, iv = int(np.floor(u)), int(np.floor(v))
    fu, fv = u - iu, v - iv
    px, py = fu * w, fv * h
    xi, yi = min(int(px // 1), w - 1), min(int(py // 1), h - 1)
    col, row = xi // tx, yi // ty
    lx, ly = xi - col * tx, yi - row * ty
    cx, cy = iu * nx + col, iv * ny + row

    def choice(a, b):
        return int(hash_vertex(np.int64(a), np.int64(b), synth.seed)) % k

    own = choice(cx, cy)
    vc, hc = t.vertical_cuts.numpy(), t.horizontal_cuts.numpy()
    sx = sy = 0
    if lx < mx and lx < vc[col, row, choice(cx - 1, cy), own, ly]:
        sx = -1
    elif lx >= tx - mx and lx - tx >= vc[(col + 1) % nx, row, own, choice(cx + 1, cy), ly]:
        sx = 1
    if ly < my and ly < hc[col, row, choice(cx, cy - 1), own, lx]:
        sy = -1
    elif ly >= ty - my and ly - ty >= hc[col, (row + 1) % ny, own, choice(cx, cy + 1), lx]:
        sy = 1
    chosen = choice(cx + sx, cy + sy)
    ox, oy = (int(x) for x in t.offsets[chosen])
    return chosen, ((px + ox) % w, (py + oy) % h)


# ---------------------------------------------------------------- structure analysis
def test_autocorrelation_matches_brute_force_sum():
    rng = np.random.default_rng(1)
    plane = rng.normal(size=(6, 5, 2))
    z = (plane - plane.mean((0, 1))) / plane.std((0, 1))
    ref = np.zeros((6, 5))
    for dy, dx in itertools.product(range(6), range(5)):
        ref[dy, dx] = (z * np.roll(z, (-dy, -dx), axis=(0, 1))).sum()
    np.testing.assert_allclose(autocorrelation(plane), ref / ref[0, 0], atol=1e-12)


def test_structure_strength_separates_lattices_from_noise():
    structured = analyze_structure(_lattice_exemplar())
    assert structured.strength > 0.8 and structured.structured
    lags = {(dx, dy) for dx, dy, value in structured.peaks if value > 0.8}
    assert {(8, 0), (0, 8)} <= lags  # the element lattice
    noise = analyze_structure(torch.randn(64, 64, 4, generator=torch.Generator().manual_seed(0)))
    assert noise.strength < 0.2 and not noise.structured
    assert STRUCTURE_THRESHOLD == pytest.approx(0.5)


def test_auto_chooses_struct_for_lattices_and_hist_for_noise():
    choice = choose_method(_lattice_exemplar())
    assert choice.method == "struct" and "struct" in choice.line and "structure strength" in choice.line
    assert choose_method(torch.rand(32, 32, 3, generator=torch.Generator().manual_seed(2))).method == "hist"
    synth = make_synthesizer("auto", _lattice_exemplar(), seed=3)
    assert isinstance(synth, CellQuilting) and synth.choice.method == "struct" and synth.seed == 3
    assert make_synthesizer("hist", _lattice_exemplar()).choice is None


# ---------------------------------------------------------------- the method
def _seam_cost(err, cut) -> float:
    """A seam's cost in plain Python: the error of each row's first texel of the right copy, plus, where the seam
    moves from column ``a`` to ``b`` between two rows, ``min`` of the two rows' errors at each column strictly
    between (:func:`dynbtf.synthesis.quilting.min_error_seam`)."""
    total = sum(float(err[r, c]) for r, c in enumerate(cut))
    for r in range(1, len(cut)):
        low, high = sorted((int(cut[r - 1]), int(cut[r])))
        total += sum(min(float(err[r - 1, k]), float(err[r, k])) for k in range(low + 1, high))
    return total


def test_offsets_are_lattice_vectors_and_cuts_are_minimal_seams():
    exemplar = _lattice_exemplar(period=8, repeats=4)
    tables = build_cell_tables(exemplar, offsets=6, cells=2)
    offsets = tables.offsets.numpy()
    assert tuple(offsets[0]) == (0, 0) and tables.count == 6
    assert ((offsets % 8) == 0).all()  # every copy is shifted by whole elements
    # one vertical edge's cut against the cheapest seam found by relaxing every move between rows in plain Python;
    # a seam texel costs the two copies' squared difference plus SPREAD_WEIGHT times the spread of all copies there,
    # plus CROSSING_WEIGHT times the mean difference of two unrelated texels off the tables' joints
    x = exemplar.numpy().astype(np.float64)
    z = (x - x.mean((0, 1))) / x.std((0, 1))
    mx = tables.margin[0]
    rows, cols = np.arange(0, 16), np.arange(16 - mx, 16 + mx)  # the edge at x = 16 (cell column 1), cell row 0
    copies = np.stack([z[(rows[:, None] + dy) % 32, (cols[None] + dx) % 32] for dx, dy in offsets])
    spread = copies.var(0).sum(-1)  # every copy's spread at each band texel
    joints = tables.joints.numpy().astype(bool)[(rows[:, None]) % 32, cols[None] % 32]
    crossing = np.where(joints, 0.0, CROSSING_WEIGHT * 2.0 * z.var((0, 1)).sum())
    assert 0 < joints.mean() < 1  # the crossing cost takes part
    for a, b in ((1, 2), (0, 5), (4, 3)):
        err = ((copies[a] - copies[b]) ** 2).sum(-1) + SPREAD_WEIGHT * spread + crossing
        cut = tables.vertical_cuts[1, 0, a, b].numpy().astype(int) + mx
        costs = {c: float(err[0, c]) for c in range(2 * mx)}
        for r in range(1, err.shape[0]):
            costs = {c: float(err[r, c]) + min(costs[p] + _seam_cost(err[r - 1:r + 1], [p, c]) - float(err[r - 1, p])
                                               - float(err[r, c]) for p in costs) for c in range(2 * mx)}
        assert _seam_cost(err, cut) == pytest.approx(min(costs.values()), rel=1e-9)


BOND = (64, 16, 8, 2)  # exemplar side, brick width and height, joint width (texels)


def _bricks(x, y):
    """The brick ``(course, column)`` of integer texels ``x, y`` of :data:`BOND`'s running bond (any repeat), and
    whether the texel is in a joint."""
    _, brick_w, brick_h, joint = BOND
    course = np.floor_divide(y, brick_h)
    shifted = x + (brick_w // 2) * (course % 2)
    joint_texel = (np.mod(shifted, brick_w) < joint) | (np.mod(y, brick_h) < joint)
    return course, np.floor_divide(shifted, brick_w), joint_texel


def _running_bond(palette: str) -> torch.Tensor:
    """:data:`BOND`'s wall ``(64, 64, 3)``, black joints. ``palette``: "distinct" (every brick its own random colour)
    or "two clays" (each brick one of two colours, with a faint per-texel grain: many bricks of one colour, between
    which a cut is nearly free)."""
    side, brick_w, brick_h, _ = BOND
    yy, xx = np.mgrid[0:side, 0:side]
    course, column, in_joint = _bricks(xx, yy)
    rng = np.random.default_rng(1)
    brick = course % (side // brick_h), column % (side // brick_w)
    if palette == "distinct":
        colour = rng.random((side // brick_h, side // brick_w, 3))[brick]
    else:
        clay = rng.integers(0, 2, (side // brick_h, side // brick_w))[brick]
        colour = np.array([[0.6, 0.3, 0.2], [0.4, 0.35, 0.3]])[clay] + 0.01 * rng.random((side, side, 3))
    return torch.from_numpy(np.where(in_joint[..., None], 0.0, colour).astype(np.float32))


def _running_bond_bricks(palette: str, seeds=range(3)) -> tuple[int, int, int]:
    """``(whole, broken, misread)``: bricks of a 6 x 6-repeat window of ``struct`` on :func:`_running_bond`'s wall
    over ``seeds``, a brick broken when its texels read more than one source brick; ``misread``: brick texels that
    read a joint."""
    side, brick_w, brick_h, _ = BOND
    exemplar = _running_bond(palette)
    window = 6 * side
    gy, gx = np.mgrid[0:window, 0:window].reshape(2, -1)
    uv = torch.from_numpy(np.stack([1e6 + (gx + 0.5) / side, 2e6 + (gy + 0.5) / side], -1))
    out_course, out_column, out_joint = _bricks(gx, gy)
    whole = broken = misread = 0
    for seed in seeds:
        read, _ = CellQuilting(exemplar, seed=seed, fast=False).read_positions(uv)
        src_course, src_column, src_joint = _bricks(np.floor(read[:, 0].numpy()).astype(np.int64),
                                                    np.floor(read[:, 1].numpy()).astype(np.int64))
        inside = ~out_joint
        source = (src_course % (side // brick_h)) * (side // brick_w) + src_column % (side // brick_w)
        target = out_course * window + out_column
        keep = inside & ~src_joint
        misread += int((inside & src_joint).sum())
        pairs = np.unique(np.stack([target[keep], source[keep]]), axis=1)
        per_brick = np.unique(pairs[0], return_counts=True)[1]
        whole += int((per_brick == 1).sum())
        broken += int((per_brick > 1).sum())
    return whole, broken, misread


@pytest.mark.parametrize("palette", ["distinct", "two clays"])
def test_seams_keep_every_brick_of_a_running_bond_whole(palette):
    """Bricks of a running bond (staggered head joints) each come whole from one source: the seams follow the
    joints, also where many bricks share a colour. Straight-ish cuts (one column per row) cross about a quarter of
    the bricks of the distinct wall."""
    whole, broken, misread = _running_bond_bricks(palette)
    assert whole > 1000 and broken == 0 and misread == 0  # and a brick texel reads a brick texel


def test_without_the_crossing_cost_seams_cut_through_bricks_of_one_colour(monkeypatch):
    """What :func:`~dynbtf.synthesis.cell_quilting.joint_crossing` is for: with it off, the copies' difference and
    spread make a cut between two bricks of one clay nearly free, and the seams take it."""
    monkeypatch.setattr(cell_quilting, "CROSSING_WEIGHT", 0.0)
    whole, broken, _ = _running_bond_bricks("two clays")
    assert broken > 0.01 * (whole + broken)


def test_broken_elements_found_from_the_joints_agree_with_the_walls_geometry(monkeypatch):
    """:func:`~dynbtf.synthesis.elements.broken_elements` finds the elements from the joint map alone; on the
    running bond, with seams that break some bricks (crossing cost off), its share agrees with the count from the
    known geometry, and the struct tables' joint map is the wall's."""
    monkeypatch.setattr(cell_quilting, "CROSSING_WEIGHT", 0.0)
    exemplar = _running_bond("two clays")
    whole, broken, _ = _running_bond_bricks("two clays", seeds=[0])
    synth = CellQuilting(exemplar, seed=0, fast=False)
    side = BOND[0]
    yy, xx = np.mgrid[0:side, 0:side]
    assert (synth.prepared.joints.numpy().astype(bool) == _bricks(xx, yy)[2]).all()
    share, counted = broken_elements(lambda uv: synth.read_positions(uv)[0], synth.prepared.joints.numpy(), repeats=6)
    assert broken > 0 and counted > 0.9 * (whole + broken)
    assert share == pytest.approx(broken / (whole + broken), abs=0.005)


def test_a_strictly_periodic_exemplar_is_reproduced_exactly():
    """Every offset is a lattice vector: without per-element variation the copies are the exemplar itself."""
    exemplar = _lattice_exemplar(variation=0.0)
    exemplar = exemplar + 0.0  # strictly periodic with period 8
    synth = CellQuilting(exemplar, seed=5, cells=2)
    uv = torch.rand(4096, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 40 - 20
    tile = make_synthesizer("tile", exemplar)
    torch.testing.assert_close(synth(uv), tile(uv), atol=1e-5, rtol=0)


@pytest.mark.parametrize("base", [0.0, 1e3, 2.0**33, 2.0**45])
def test_read_positions_match_a_scalar_reference_far_from_the_origin(base):
    synth = CellQuilting(_lattice_exemplar(), seed=11, cells=2)
    rng = np.random.default_rng(int(base) % 1000 + 3)
    points = base + rng.random((300, 2)) * 3.0
    positions, chosen = synth.read_positions(torch.from_numpy(points))
    for (u, v), pos, k in zip(points, positions.numpy(), chosen.numpy()):
        ref_k, ref_pos = _brute_force_read(synth, float(u), float(v))
        assert k == ref_k
        assert tuple(pos) == pytest.approx(ref_pos, abs=1e-9)


def test_fused_kernel_matches_the_torch_reference():
    exemplar = _lattice_exemplar(channels=5)
    fast = CellQuilting(exemplar, seed=2)
    slow = CellQuilting(exemplar, seed=2, fast=False, prepared=fast.prepared)
    uv = torch.from_numpy(np.random.default_rng(4).random((20000, 2)) * 64 - 32 + np.array([2.0**40, -3.0]))
    torch.testing.assert_close(fast(uv), slow(uv), atol=2e-5, rtol=0)


def test_cells_change_their_offsets_and_neighbours_continue_the_lattice():
    exemplar = _lattice_exemplar(period=8, repeats=8, variation=0.2)
    synth = CellQuilting(exemplar, seed=7, cells=2)
    # texel centres of 16 x 16 cells far away
    n = 64
    base = 2.0**20
    u = base + (np.arange(16 * n) + 0.5) / n
    uv = torch.from_numpy(np.stack(np.meshgrid(u, base + (np.arange(16 * n) + 0.5) / n), -1).reshape(-1, 2))
    positions, chosen = synth.read_positions(uv)
    assert len(torch.unique(chosen)) == synth.prepared.count  # every copy is used
    # structure continues everywhere: the read position's phase in the element lattice equals the query's
    pos = positions.reshape(16 * n, 16 * n, 2).numpy()
    grid = np.stack(np.meshgrid((np.arange(16 * n) + 0.5), (np.arange(16 * n) + 0.5)), -1) % n
    np.testing.assert_allclose((pos - grid) % 8, 0.0, atol=1e-6)
    # and it is not tiling: most cells read another copy
    assert (chosen != 0).float().mean() > 0.8


def test_footprints_read_the_pyramid_at_the_point_reads():
    exemplar = _lattice_exemplar()
    synth = CellQuilting(exemplar, seed=1)
    uv = torch.from_numpy(np.random.default_rng(0).random((500, 2)) * 10)
    torch.testing.assert_close(synth(uv, footprint=torch.full((500,), 0.5)), synth(uv), atol=2e-5, rtol=0)
    mean = exemplar.mean((0, 1))
    torch.testing.assert_close(synth(uv, footprint=1e4), mean.expand(500, -1), atol=1e-5, rtol=0)


def test_bad_parameters_name_the_argument_and_the_limit():
    exemplar = _lattice_exemplar(period=8, repeats=4)  # 32 x 32
    with pytest.raises(InputError, match="cells: 3 cells per repeat do not divide the exemplar's 32 texels"):
        CellQuilting(exemplar, cells=3)
    with pytest.raises(InputError, match="cells need at least 8 texels"):
        CellQuilting(exemplar, cells=8)
    with pytest.raises(InputError, match="offsets: expected an integer number of lattice offsets in \\[1, 64\\]"):
        CellQuilting(exemplar, offsets=0)
    with pytest.raises(InputError, match="margin"):
        CellQuilting(exemplar, margin=0.9)
    with pytest.raises(InputError, match="at least 8x8 texels"):
        CellQuilting(torch.rand(6, 6, 3))
    other = CellQuilting(_lattice_exemplar(period=8, repeats=8))
    with pytest.raises(InputError, match="prepared: its cut tables do not fit this 32x32 exemplar"):
        CellQuilting(exemplar, prepared=other.prepared)
    with pytest.raises(InputError, match="unknown; expected one of .*'auto'"):
        make_synthesizer("wang", exemplar)


def test_tables_depend_on_the_exemplar_and_parameters_not_the_seed():
    """What lets the material cache share one model's tables between seeds (tests/test_material_fuzz.py): the same
    contents and parameters give the same tables under any seed, other contents or parameters others."""
    exemplar = _lattice_exemplar()
    first = CellQuilting(exemplar, seed=1)
    assert first.prepared.source == "built"
    again = CellQuilting(exemplar.clone(), seed=2)
    for name in ("offsets", "vertical_cuts", "horizontal_cuts"):
        assert torch.equal(getattr(again.prepared, name), getattr(first.prepared, name))
    assert not torch.equal(CellQuilting(exemplar, seed=1, offsets=2).prepared.offsets, first.prepared.offsets)
    assert not CellQuilting.seeded_tables


def test_guide_finds_the_lattice_that_noisy_features_hide():
    rng = np.random.default_rng(5)
    appearance = _lattice_exemplar(channels=3).numpy()
    features = np.concatenate([appearance, rng.normal(size=(32, 32, 13)) * 3.0], -1)  # mostly noise channels
    assert choose_method(features).method == "hist"
    assert choose_method(features, guide=appearance).method == "struct"
    synth = make_synthesizer("auto", torch.from_numpy(features.astype(np.float32)), guide=appearance, gamma=3.0)
    assert isinstance(synth, CellQuilting)  # gamma was hist's: not passed to struct
    assert ((synth.prepared.offsets.numpy() % 8) == 0).all()
    hist = make_synthesizer("auto", torch.from_numpy(features.astype(np.float32)), gamma=3.0)
    assert hist.name == "hist" and hist.gamma == 3.0
    with pytest.raises(InputError, match="guide: expected a plane of shape \\(32, 32, G\\)"):
        CellQuilting(torch.from_numpy(features.astype(np.float32)), guide=np.zeros((16, 16, 3)))
    with pytest.raises(InputError, match="'auto': unknown parameter\\(s\\) \\['bogus'\\]"):
        make_synthesizer("auto", torch.from_numpy(features.astype(np.float32)), bogus=1)


def test_auto_method_of_a_model_is_synthesized_btfs_choice():
    """auto_method (what `dynbtf render` resolves before Mitsuba loads) chooses what synthesized_btf("auto") builds:
    both measure the decoded appearance, so a lattice the decoder shows is found even when half of the
    feature channels are noise."""
    from dynbtf.representations.triple_plane import TriplePlane
    from dynbtf.material import decoded_appearance
    from dynbtf.synthesized import auto_method
    from dynbtf.synthesized import synthesized_btf

    model = TriplePlane(32, 32, positional_channels=6, angular_channels=3, hidden=12, seed=5)
    with torch.no_grad():
        model.decoder.rest[-1].bias.add_(0.6)
        random_choice = auto_method(model)
        assert random_choice.method == synthesized_btf(model, "auto").synthesizer.name == "hist"
        element = model.f_u[:8, :8].clone()
        model.f_u.copy_(element.repeat(4, 4, 1) + 0.05 * torch.randn(32, 32, 6, generator=torch.Generator().manual_seed(1)))
    choice = auto_method(model)
    btf = synthesized_btf(model, "auto", seed=2)
    assert choice.method == btf.synthesizer.name == "struct" and choice.line == btf.synthesizer.choice.line
    guide = decoded_appearance(model)
    assert guide.shape == (32, 32, 9)
    w = torch.tensor([[0.0, 0.0, 1.0]])
    torch.testing.assert_close(guide[3, 5, :3], model.decode(model.f_u[3, 5][None], w, w)[0].float())


@pytest.mark.parametrize("grid, side, n, axis, reaches", [
    ([4, 8, 1, 2, 0.0, 0.0], 64, 2, "u", False),  # 16-texel bricks, half bond: odd rows' head joints 8 away, reach 7
    ([4, 8, 1, 2, 0.0, 0.0], 64, 1, "u", True),   # one cell: 16-texel bands
    ([4, 8, 1, 2, 0.0, 0.0], 64, 2, "v", True),   # bed joints every 8 texels: one on each edge
    ([4, 8, 1, 2, 0.0, 4.0], 64, 2, "v", True),   # ... or 4 texels off them
    ([4, 2, 0, 1, 0.0, 12.0], 64, 2, "v", False), # 32-texel rows whose bed joints lie 12 texels off the edges
    ([4, 4, 0, 1, 3.0, 3.0], 64, 2, "u", True),   # square tiles, stack bond: the joints 3 texels off every edge
    ([3, 6, 1, 2, 0.0, 0.0], 66, 2, "u", False),  # 22-texel bricks, 33-texel cells: even rows' joints 11 away
    ([1, 1, 0, 1, 5.0, 5.0], 64, 2, "u", True),   # no elements: nothing to follow
])
def test_cell_bands_reach_every_rows_joints(grid, side, n, axis, reaches):
    from dynbtf.synthesis.cell_quilting import _bands_reach_joints

    assert _bands_reach_joints(np.array(grid, dtype=np.float64), side, n, 0.25, axis) is reaches


def test_auto_cells_are_one_across_a_running_bond_and_two_over_square_tiles():
    """The running bond of the test above: two 32-texel cells would leave alternate rows' head joints one texel out
    of the seams' reach, so ``auto`` takes one cell across (two up); square tiles keep two by two."""
    y, x = np.mgrid[0:64, 0:64]
    course = y // 8
    bond = ((x + 8 * (course % 2)) % 16 < 2) | (y % 8 < 2)
    colour = np.random.default_rng(2).random((8, 4, 3))[course, ((x + 8 * (course % 2)) // 16) % 4]
    wall = torch.from_numpy(np.where(bond[..., None], 0.0, colour).astype(np.float32))
    assert build_cell_tables(wall).cells == (1, 2)
    assert build_cell_tables(wall, cells=2).cells == (2, 2)  # a number is kept as given
    tiles = ((x % 16) < 2) | ((y % 16) < 2)
    colour = np.random.default_rng(3).random((4, 4, 3))[y // 16, x // 16]
    tiled = torch.from_numpy(np.where(tiles[..., None], 0.0, colour).astype(np.float32))
    assert build_cell_tables(tiled).cells == (2, 2)
