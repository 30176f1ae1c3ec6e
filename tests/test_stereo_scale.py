"""The parallax fit at scale. Plane-sweep stereo: blocks of texels change nothing; a spread subset
of views and the lights nearest the normal still recover a known height; the fitter's choice for
large BTFs. Training: visible points marched on demand equal a whole march."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dynbtf.data.array import ArrayBTF
from dynbtf.data.directions import direction_set
from dynbtf.errors import InputError
from dynbtf.representations.parallax import ParallaxTriplePlane, view_offsets
from dynbtf.texture import fetch_wrap
from dynbtf.training.fitters import parallax_stereo_options
from dynbtf.training.stereo_height import (CHUNK_ALIGN, auto_stereo_options, spread_views, stereo_height)

pytestmark = pytest.mark.usefixtures("single_thread")

SIZE = 48


def true_height() -> torch.Tensor:
    """``(SIZE, SIZE)`` uv units: a smooth periodic relief of +-3 texels."""
    u = (torch.arange(SIZE, dtype=torch.float64) + 0.5) / SIZE
    return 3.0 / SIZE * torch.sin(2 * math.pi * u)[:, None] * torch.cos(2 * math.pi * u)[None, :]


@pytest.fixture(scope="module")
def relief_btf() -> ArrayBTF:
    """A textured Lambertian relief of known height, UBO2003 views, three lights near the normal: the image
    of view ``w`` at reference point ``p`` shows the texture at the surface point ``q = p + z(q) s_w``."""
    rng = np.random.default_rng(0)
    texture = torch.from_numpy(rng.random((SIZE, SIZE, 3)))
    texture = (texture + texture.roll(1, 0) + texture.roll(1, 1) + texture.roll((1, 1), (0, 1))) / 4
    height = true_height()[..., None]
    views = direction_set("ubo2003")
    lights = np.array([[0.0, 0.0, 1.0], [math.sin(0.15), 0.0, math.cos(0.15)], [0.0, math.sin(0.2), math.cos(0.2)],
                       [math.sin(1.0), 0.0, math.cos(1.0)]])
    u = (torch.arange(SIZE, dtype=torch.float64) + 0.5) / SIZE
    p = torch.stack(torch.meshgrid(u, u, indexing="xy"), -1).reshape(-1, 2)  # (N, 2): (u = column, v = row)
    images = []
    for w in views:
        s = view_offsets(torch.as_tensor(w, dtype=torch.float64))
        q = p.clone()
        for _ in range(20):  # fixed point of q = p + z(q) s (contracting: |grad z| |s| < 1 here)
            q = p + fetch_wrap(height, q) * s
        images.append(fetch_wrap(texture, q).reshape(SIZE, SIZE, 3).numpy())
    values = np.stack([[image * (0.5 + 0.5 * l[2]) for l in lights] for image in images])
    return ArrayBTF(values, views, lights, name="relief")


def texels_rmse(estimate: torch.Tensor) -> float:
    return float((estimate - true_height()).pow(2).mean().sqrt()) * SIZE


def test_blocks_of_texels_change_nothing(relief_btf):
    whole = stereo_height(relief_btf, chunk_texels=SIZE * SIZE)
    for chunk in (1, CHUNK_ALIGN, 1000):  # rounded up to multiples of CHUNK_ALIGN: 256, 256, 1024 (2 + 1 blocks)
        assert torch.equal(stereo_height(relief_btf, chunk_texels=chunk), whole), chunk
    assert torch.equal(stereo_height(relief_btf), whole)
    assert texels_rmse(whole) < 0.5, texels_rmse(whole)


def test_images_are_read_view_major_and_the_grouping_of_lights_changes_nothing(relief_btf, monkeypatch):
    import dynbtf.training.stereo_height as stereo

    reads = []
    image = relief_btf.image
    monkeypatch.setattr(relief_btf, "image", lambda v, l: reads.append((v, l)) or image(v, l))
    together = stereo_height(relief_btf)  # the three lights near the normal fit in READ_BYTES: one view-major read
    n_views = relief_btf.n_views
    assert reads == [(v, l) for v in range(n_views) for l in (0, 1, 2)]
    reads.clear()
    monkeypatch.setattr(stereo, "READ_BYTES", 1)  # at least one light at a time: light-major, as many reads
    assert torch.equal(stereo_height(relief_btf), together)
    assert reads == [(v, l) for l in (0, 1, 2) for v in range(n_views)]


@pytest.mark.parametrize("views, texels", [(7, 50), (8, 50), (1, 33), (151, 100)])
@pytest.mark.parametrize("ties", [False, True])
def test_the_median_over_views_is_torch_median(views, texels, ties):
    """Any view count (for an even one the lower middle value), texel counts across the copy's tiles, ties,
    and grid_sample's layout (views, channels, texels) seen as (views, texels, channels)."""
    from dynbtf.training.stereo_height import _median_views

    values = torch.rand(views, 3, texels, generator=torch.Generator().manual_seed(views))
    if ties:
        values = (4 * values).floor()
    seen = values.transpose(1, 2)
    assert torch.equal(_median_views(seen), seen.median(0).values)


def test_spread_views_and_nearest_lights_still_recover_the_height(relief_btf):
    every = texels_rmse(stereo_height(relief_btf))
    subset = stereo_height(relief_btf, max_views=16, max_lights=1)
    assert texels_rmse(subset) < max(0.5, 1.5 * every), (texels_rmse(subset), every)
    # one light: the one nearest the normal (light 0), not the others within 15 degrees
    only_first = ArrayBTF(relief_btf.values[:, :1], relief_btf.views, relief_btf.lights[:1])
    assert torch.equal(subset, stereo_height(only_first, max_views=16))
    with pytest.raises(InputError, match="max_views"):
        stereo_height(relief_btf, max_views=1)
    with pytest.raises(InputError, match="max_lights"):
        stereo_height(relief_btf, max_lights=0)


def test_spread_views_cover_the_hemisphere():
    views = direction_set("ubo2014")
    chosen = spread_views(views, 32)
    assert len(chosen) == 32 and len(set(chosen.tolist())) == 32 and list(chosen) == sorted(chosen)
    assert int(np.argmax(views[:, 2])) in chosen  # the normal view first
    # every view lies within the largest gap of the subset's farthest-point cover: about 20 degrees here
    angle = np.degrees(np.arccos(np.clip(views @ views[chosen].T, -1, 1))).min(1)
    assert angle.max() < 25.0, angle.max()
    assert np.array_equal(spread_views(views, 500), np.arange(len(views)))


def test_auto_options_only_for_large_btfs():
    class Shape:
        def __init__(self, size, n_views):
            self.height = self.width = size
            self.n_views = n_views

    assert auto_stereo_options(Shape(128, 81)) == {}
    assert auto_stereo_options(Shape(400, 151)) == {"max_views": 32, "max_lights": 3}
    # what the parallax fitter and --repr auto's evidence sweep with: the automatic subset, overridden by the user's
    assert parallax_stereo_options(Shape(400, 151), {"max_lights": 5, "max_height": 0.05}) == {
        "max_views": 32, "max_lights": 5, "max_height": 0.05}
    assert parallax_stereo_options(Shape(128, 81), None) == {}


def test_visible_points_marched_on_demand_equal_a_whole_march():
    """Training's visible-point table, filled texel block by texel block (as a step asks), equals the
    table of one march of every texel, bit for bit."""
    model = ParallaxTriplePlane(24, 32)
    relief = torch.nn.functional.avg_pool2d(torch.rand(1, 1, 24, 32, generator=torch.Generator().manual_seed(1)), 5,
                                            1, 2, count_include_pad=False)[0, 0]
    model.set_height(0.1 * relief)
    every = torch.arange(24 * 32)[None]
    for w in torch.as_tensor(direction_set("ubo2003")[::20], dtype=torch.float32):
        model._visible_cache.clear()
        whole = [t[0].clone() for t in model._visible_texel_points(w[None], every)[:2]]
        model._visible_cache.clear()
        for block in torch.randperm(24 * 32, generator=torch.Generator().manual_seed(2)).split(100):
            points, heights, _ = model._visible_texel_points(w[None], block[None])
            assert torch.equal(points[0], whole[0][block]) and torch.equal(heights[0], whole[1][block])
    # several views' blocks in one march, as a training step asks
    views = torch.as_tensor(direction_set("ubo2003")[::7], dtype=torch.float32)
    wholes = [[t[0].clone() for t in model._visible_texel_points(w[None], every)[:2]] for w in views]
    model._visible_cache.clear()
    order = torch.randperm(24 * 32, generator=torch.Generator().manual_seed(3))
    for blocks in order.reshape(-1, len(views), 8)[:5]:  # steps of (views, 8 texels each)
        model._visible_texel_points(views, blocks)
    assert 0 < int(model._visible_cache.marched.sum()) == 5 * len(views) * 8 < len(views) * 24 * 32
    points, heights, slots = model._visible_texel_points(views, every.expand(len(views), -1))  # the rest
    assert slots.tolist() == list(range(len(views)))
    for p, h, (p_whole, h_whole) in zip(points, heights, wholes):
        assert torch.equal(p, p_whole) and torch.equal(h, h_whole)


def test_visible_texel_cache_matches_views_exactly_and_starts_over_when_full(monkeypatch):
    from dynbtf.representations.parallax import VisibleTexelCache

    cache = VisibleTexelCache(10, aspect=2.0)
    views = torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.0, 1.0]])
    texels = torch.tensor([[1, 2], [2, 3], [2, 5]])
    rows, todo = cache.lookup(views, texels)
    assert rows.tolist() == [[1, 2], [12, 13], [2, 5]] and todo.tolist() == [1, 2, 12, 13, 2, 5]  # (2: twice)
    # each view's slopes: (w_x, w_y) / w_z with v times the aspect, kept with its slot
    below = torch.tensor([[0.6, 0.8, -0.01]], dtype=torch.float64)  # below the horizon: marched vertically
    assert cache.slots(below).tolist() == [2]
    assert cache.march_slopes[:3].tolist() == [[0, 0], [float(np.float32(0.6)) / float(np.float32(0.8)), 0], [0, 0]]
    assert cache.fetch_slopes.dtype == np.float32 and cache.fetch_slopes[1].tolist() == [np.float32(0.6) / np.float32(0.8), 0]
    assert cache.fetch_slopes[2].tolist() == [np.float32(0.6 / 1e-6), np.float32(2 * 0.8 / 1e-6)]  # as given, clamped
    cache.clear()
    rows, todo = cache.lookup(views, texels)
    cache.store(todo, torch.stack([todo, -todo], 1).float(), 0.5 * todo.float())  # a row's value: its own
    points, heights = cache.read(rows)
    assert points.tolist() == [[[1, -1], [2, -2]], [[12, -12], [13, -13]], [[2, -2], [5, -5]]]
    assert heights.tolist() == [[0.5, 1], [6, 6.5], [1, 2.5]]
    rows, todo = cache.lookup(views[1:2], torch.tensor([[3, 4]]))
    assert rows.tolist() == [[13, 14]] and todo.tolist() == [14]  # texel 3 of view 1 is held
    cache.forget_rows()
    assert cache.lookup(views[:1], torch.tensor([[1]]))[1].tolist() == [1]
    monkeypatch.setattr(VisibleTexelCache, "MAX_VIEWS", 3)
    rows, _ = cache.lookup(torch.tensor([[0.1, 0.0, 0.99], [0.2, 0.0, 0.98]]), torch.tensor([[0], [0]]))
    assert cache.count == 2 and rows.tolist() == [[0], [10]]  # two known + two new > 3: started over
