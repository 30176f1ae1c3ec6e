"""Parallax (kind triple-parallax): the ray march, stereo height, the model, its training and synthesis."""

import sys

import numpy as np
import pytest
import torch

from dynbtf.data.open import open_btf
from dynbtf.data.simulator.geometry import trace_view
from dynbtf.errors import InputError
from dynbtf.representations.model_file import load_model, save_model
from dynbtf.representations.parallax import ParallaxTriplePlane, march_visible_uv
from dynbtf.synthesized import synthesized_btf
from dynbtf.texture import fetch_wrap
from dynbtf.training import TrainConfig, checkpoint_path, fit, held_out_split
from dynbtf.training.evaluate import evaluate_model
from dynbtf.training.fitters import get_fitter
from dynbtf.training.stereo_height import stereo_height

from interrupt import Stop, stop_at

pytestmark = pytest.mark.usefixtures("single_thread")


def unit(v):
    return torch.nn.functional.normalize(torch.as_tensor(v, dtype=torch.float64), dim=-1)


def random_views(n, generator, min_z=0.25):
    w = torch.randn(n, 3, dtype=torch.float64, generator=generator)
    w[:, 2] = w[:, 2].abs() + min_z
    return unit(w)


@pytest.fixture(scope="module")
def stone():
    """A simulated stone at 32 x 32 texels: relief with a known height field."""
    return open_btf("sim:stone?size=32")


def texel_heights(btf) -> torch.Tensor:
    """The simulator's true height ``(H, W)`` (uv units) at the texel centres."""
    renderer = btf.renderer
    first = renderer.stride // 2
    return renderer.height.double()[first::renderer.stride, first::renderer.stride]


def test_march_on_a_tilted_plane_matches_the_closed_form():
    """h(p) = c + g . p: the ray uv + z s meets it at z = (c + g . uv) / (1 - g . s)."""
    generator = torch.Generator().manual_seed(0)
    uv = torch.rand(500, 2, dtype=torch.float64, generator=generator)
    w = random_views(500, generator, min_z=0.5)
    c, g = 0.05, torch.tensor([0.03, -0.02], dtype=torch.float64)
    slope = w[:, :2] / w[:, 2:3]
    z = (c + uv @ g) / (1 - slope @ g)
    hit = march_visible_uv(uv, w, lambda p: c + p @ g, h_min=-0.5, h_max=0.5, step=0.01)
    torch.testing.assert_close(hit, uv + z[:, None] * slope, atol=1e-12, rtol=0)


def test_march_agrees_with_the_simulator_trace(stone, monkeypatch):
    """Our march through the bilinear texel height == the simulator's own tracer (another implementation),
    both with fine steps (with coarse ones each misses different thin ridges)."""
    from dynbtf.data.simulator import geometry

    monkeypatch.setattr(geometry, "STEP_CELLS", 0.05)
    height = texel_heights(stone)
    rows, cols = torch.meshgrid((torch.arange(32, dtype=torch.float64) + 0.5) / 32,
                                (torch.arange(32, dtype=torch.float64) + 0.5) / 32, indexing="ij")
    centres = torch.stack([cols.reshape(-1), rows.reshape(-1)], dim=-1)
    for v in range(0, stone.n_views, 7):
        w = torch.as_tensor(stone.views[v], dtype=torch.float64)
        reference, _ = trace_view(height, w)
        hit = march_visible_uv(centres, w.expand(len(centres), 3),
                               lambda p: fetch_wrap(height[..., None], p)[:, 0], h_min=float(height.min()),
                               h_max=float(height.max()), step=0.05 / 32)
        distance = (hit - reference).norm(dim=-1) * 32  # texels
        assert float(distance.mean()) < 0.01 and float(distance.quantile(0.99)) < 0.1, v
        if w[2] > 0.9999:  # normal view: exactly the texel itself
            assert torch.equal(hit, centres)


def bilinear_height(plane):
    """A float64 bilinear, periodic fetch written out by hand (texel centres at (j + 0.5) / W): the height the
    compiled kernel fetches, for the torch march to call."""
    rows, cols = plane.shape

    def height_at(p):
        frac = p - p.floor()
        x, y = frac[:, 0] * cols + 0.5, frac[:, 1] * rows + 0.5
        x0, y0 = x.floor(), y.floor()
        wx, wy = x - x0, y - y0
        j0, j1 = (x0.long() - 1) % cols, x0.long() % cols
        i0, i1 = (y0.long() - 1) % rows, y0.long() % rows
        top = (1 - wx) * plane[i0, j0] + wx * plane[i0, j1]
        return (1 - wy) * top + wy * ((1 - wx) * plane[i1, j0] + wx * plane[i1, j1])
    return height_at


@pytest.mark.parametrize("shape", [(24, 24), (16, 40)])
def test_compiled_march_through_a_plane_equals_the_torch_march(shape):
    """march_visible_uv given a CPU height plane runs the compiled kernel; given a function, the torch loop.
    Through the same bilinear field (rough, wrapped, far-away uv, steep and vertical views) they agree to
    float64 rounding, and the kernel fetches the plane as fetch_wrap does."""
    generator = torch.Generator().manual_seed(3)
    plane = 0.04 * torch.rand(*shape, dtype=torch.float64, generator=generator)
    points = torch.rand(300, 2, dtype=torch.float64, generator=generator) * 6 - 3
    torch.testing.assert_close(bilinear_height(plane)(points), fetch_wrap(plane[..., None], points)[:, 0],
                               atol=1e-15, rtol=0)
    n = 4000
    uv = torch.rand(n, 2, dtype=torch.float64, generator=generator) * 4 - 2
    uv[:10] += 1e6
    w = random_views(n, generator, min_z=0.08)
    w[-5:] = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    aspect = shape[1] / shape[0]
    options = dict(h_min=float(plane.min()), h_max=float(plane.max()), step=0.5 / max(shape),
                   max_step=8.0 / max(shape), aspect=aspect)
    compiled = march_visible_uv(uv, w, plane, **options)
    reference = march_visible_uv(uv, w, bilinear_height(plane), **options)
    assert compiled.dtype == torch.float64 and compiled.shape == (n, 2)
    torch.testing.assert_close(compiled, reference, atol=1e-9, rtol=0)
    torch.testing.assert_close(compiled[-5:], uv[-5:], atol=0, rtol=0)  # vertical: the point itself
    with pytest.raises(InputError, match="height plane"):
        march_visible_uv(uv, w, plane[..., None], **options)


def test_march_rejects_bad_arguments():
    uv = torch.zeros(3, 2, dtype=torch.float64)
    with pytest.raises(InputError, match="w_view"):
        march_visible_uv(uv, torch.zeros(2, 3), lambda p: p[:, 0], h_min=0, h_max=1, step=0.1)
    with pytest.raises(InputError, match="step"):
        march_visible_uv(uv, unit(torch.ones(3, 3)), lambda p: p[:, 0], h_min=0, h_max=1, step=0)


def test_stereo_recovers_the_simulated_height(stone):
    """Plane-sweep stereo from the BTF's images alone vs the simulator's true height field (at 64^2: at
    32^2 the stone's relief is about one texel deep; measured: correlation 0.85, RMSE 0.37 texels)."""
    btf = open_btf("sim:stone?size=64")
    estimate, trusted = stereo_height(btf, return_trusted=True)
    assert torch.equal(estimate, stereo_height(btf))
    true = texel_heights(btf)
    assert estimate.shape == trusted.shape == (64, 64) and estimate.dtype == torch.float64
    assert float(trusted.double().mean()) > 0.75  # the views agree on the relief on most texels (measured 0.85)
    correlation = float(np.corrcoef(estimate.reshape(-1), true.reshape(-1))[0, 1])
    rmse, spread = float((estimate - true).pow(2).mean().sqrt()), float(true.std())
    assert correlation > 0.75 and rmse < 0.6 * spread, (correlation, rmse, spread)
    with pytest.raises(InputError, match="levels"):
        stereo_height(stone, levels=2)
    with pytest.raises(InputError, match="min_contrast"):
        stereo_height(stone, min_contrast=1.0)


def test_stereo_finds_no_relief_on_a_flat_btf():
    """relief=0: the views agree best on the reference plane; no texel may be given relief."""
    flat = open_btf("sim:stone?size=32&relief=0")
    height, trusted = stereo_height(flat, return_trusted=True)
    assert float(height.abs().max()) * 32 < 0.05
    assert float(trusted.double().mean()) < 0.1  # the reference plane is as good as any height: not trusted
    with pytest.raises(InputError, match="window"):
        stereo_height(stone, window=2)


def test_model_shapes_plane_and_fetch_point():
    model = ParallaxTriplePlane(8, 8, seed=1)
    height = 0.02 * torch.rand(8, 8)
    model.set_height(height)
    assert model.positional_plane().shape == (8, 8, 17)
    torch.testing.assert_close(model.positional_plane()[..., -1], height / model.height_scale)
    uv, w = torch.rand(4, 5, 2), unit(torch.rand(4, 5, 3) + torch.tensor([0, 0, 0.5])).float()
    assert model(uv, w, w).shape == (4, 5, 3)
    # the value is the decode of the positional plane at the visible point
    visible = model.visible_uv(uv, w)
    torch.testing.assert_close(model(uv, w, w), model.decode(model.positional_features(visible), w, w))
    straight_up = torch.tensor([0.0, 0.0, 1.0]).expand(4, 5, 3)
    torch.testing.assert_close(model.visible_uv(uv, straight_up), uv.double(), atol=1e-7, rtol=0)
    with pytest.raises(InputError, match="height"):
        model.set_height(torch.zeros(4, 4))
    with pytest.raises(InputError, match="height_scale"):
        ParallaxTriplePlane(8, 8, height_scale=0)


def test_fused_loss_matches_the_plain_loss_and_gradients():
    model = ParallaxTriplePlane(8, 8, seed=2)
    model.set_height(0.03 * torch.rand(8, 8))
    generator = torch.Generator().manual_seed(3)
    views = random_views(2, generator).float()
    w_view = views.repeat_interleave(3, 0)  # 2 groups x 3 images, one view per group
    w_light = random_views(6, generator).float()
    texels = torch.arange(64)
    target = torch.rand(3, 64, 3, generator=generator)

    def plain():
        predictions = [model.predict_texel_images(w_view[3 * g:3 * g + 3], w_light[3 * g:3 * g + 3],
                                                  texels[32 * g:32 * g + 32]) for g in range(2)]
        return (torch.cat(predictions, dim=1) - target).abs().mean()

    reference = plain()
    reference.backward()
    expected = {n: p.grad.clone() for n, p in model.named_parameters()}
    model.zero_grad()
    fused = model.texel_image_l1_loss(w_view, w_light, target, texels, texel_groups=2)
    fused.backward()
    torch.testing.assert_close(fused, reference, atol=1e-6, rtol=1e-5)
    for name, p in model.named_parameters():
        torch.testing.assert_close(p.grad, expected[name], atol=1e-6, rtol=1e-4, msg=name)
    assert float(expected["f_u"].abs().sum()) > 0
    with pytest.raises(InputError, match="share one view"):
        model.texel_image_l1_loss(w_light, w_light, target, texels, texel_groups=2)


def test_gradients_reach_the_positional_plane_at_the_visible_point():
    """gradcheck of the query in float64; the fetch moves with the view."""
    model = ParallaxTriplePlane(6, 6, seed=3).double()
    model.set_height(0.05 * torch.rand(6, 6, dtype=torch.float64))
    uv = torch.rand(7, 2, dtype=torch.float64)
    w = unit(torch.rand(7, 3) + torch.tensor([0, 0, 0.4]))
    plane = model.f_u.detach().clone().requires_grad_(True)

    def query(f_u):
        with torch.no_grad():
            model.f_u.copy_(f_u.detach())
        features = torch.cat([fetch_wrap(f_u, model.visible_uv(uv, w)),
                              fetch_wrap(model.height_channel[..., None], model.visible_uv(uv, w))], dim=-1)
        return model.decode(features, w, w)

    assert torch.autograd.gradcheck(query, (plane,))
    torch.testing.assert_close(query(plane), model(uv, w, w))


def test_save_load_is_bit_exact_with_the_height(tmp_path):
    model = ParallaxTriplePlane(8, 8, seed=4, height_scale=0.01)
    model.set_height(0.02 * torch.randn(8, 8))
    save_model(tmp_path / "m.dbtfm", model, {"note": "test"})
    loaded, meta = load_model(tmp_path / "m.dbtfm")
    assert type(loaded) is ParallaxTriplePlane and meta["kind"] == "triple-parallax"
    for (name, a), b in zip(model.state_dict().items(), loaded.state_dict().values()):
        assert torch.equal(a, b), name
    uv, w = torch.rand(20, 2), unit(torch.rand(20, 3) + torch.tensor([0, 0, 0.3])).float()
    assert torch.equal(model(uv, w, w), loaded(uv, w, w))


def test_fit_uses_view_coherent_batches_resumes_and_beats_the_flat_model(tmp_path, stone, monkeypatch):
    """Every step's groups each see one view; a resumed run ends where an uninterrupted one does; with
    its stereo height the model fits the stone's held-out pairs better than the Triple Plane; a rerun on
    the finished output returns it without sweeping the stereo again."""
    config = TrainConfig(epochs=3, texel_groups=4, images_per_step=8, lr_scale=6.0, seed=0, workers=1,
                         monitor_pairs=0, device="cpu", checkpoint_every=50, precision="fp32")
    seen = []
    original = ParallaxTriplePlane.texel_image_l1_loss

    def spy(self, w_view, w_light, target, texels=None, **kw):
        seen.append(w_view.reshape(kw["texel_groups"], -1, 3))
        return original(self, w_view, w_light, target, texels, **kw)

    ParallaxTriplePlane.texel_image_l1_loss = spy
    try:
        result = get_fitter("triple-parallax")(stone, tmp_path / "p.dbtfm", config, progress=False)
    finally:
        ParallaxTriplePlane.texel_image_l1_loss = original
    assert seen and all(bool((g == g[:, :1]).all()) for g in seen)
    train, held = held_out_split(stone.n_views, stone.n_lights, 0.05, 0)
    flat = get_fitter("triple")(stone, tmp_path / "t.dbtfm", config, progress=False).representation
    parallax_psnr = evaluate_model(result.representation, stone, held, progress=False).mean["psnr"]
    flat_psnr = evaluate_model(flat, stone, held, progress=False).mean["psnr"]
    assert parallax_psnr > flat_psnr + 1.0, (parallax_psnr, flat_psnr)
    assert result.metadata["provenance"]["height_field"]["method"].startswith("plane-sweep stereo")

    def no_sweep(*args, **kwargs):
        raise AssertionError("the stereo was swept again for a finished fit")

    with monkeypatch.context() as patch:
        patch.setattr(sys.modules["dynbtf.training.stereo_height"], "stereo_height", no_sweep)
        again = get_fitter("triple-parallax")(stone, tmp_path / "p.dbtfm", config, progress=False)
    assert again.finished and torch.equal(again.representation.height_channel, result.representation.height_channel)

    out = tmp_path / "resumed.dbtfm"
    first = ParallaxTriplePlane(32, 32, seed=0)
    first.set_height(stereo_height(stone))  # what the fitter started from
    with pytest.raises(Stop):
        fit(first, stone, config, out, progress=False, callback=stop_at(7))
    assert checkpoint_path(out).exists()
    resumed = fit(ParallaxTriplePlane(32, 32, seed=0), stone, config, out, progress=False)  # height from the checkpoint
    for (name, a), b in zip(result.representation.state_dict().items(), resumed.representation.state_dict().values()):
        assert torch.equal(a, b), name


def test_synthesized_btf_marches_through_the_synthesized_height():
    model = ParallaxTriplePlane(16, 16, seed=5)
    model.set_height(0.04 * torch.rand(16, 16))
    generator = torch.Generator().manual_seed(6)
    uv = torch.rand(300, 2, dtype=torch.float64, generator=generator)
    wv, wl = random_views(300, generator).float(), random_views(300, generator).float()
    # plain tiling at scale 1 is the model itself: the march through the "synthesized" height is the model's
    tiled = synthesized_btf(model, "tile", scale=1.0).eval(uv + 5.0, wv, wl)
    torch.testing.assert_close(tiled, model(uv, wv, wl).detach(), atol=1e-4, rtol=0)
    # histogram-preserving blending: the value is the decode at the visible point of the synthesized field
    btf = synthesized_btf(model, "hist", scale=4.0, seed=1)
    points = uv * 4.0
    visible = model.visible_uv(points, wv, btf.synthesizer)
    expected = model.decode(btf.synthesizer(visible), wv, wl)
    torch.testing.assert_close(btf.eval(uv, wv, wl), expected.detach().float(), atol=1e-4, rtol=0)
    assert float((visible - points).abs().max()) > 1e-3  # the fetch did move


def pebble_model(size=32, seed=7):
    """A parallax model whose height is skewed (flat ground, round pebbles: far from Gaussian) and whose first
    feature channel is the height itself, the others random."""
    model = ParallaxTriplePlane(size, size, seed=seed)
    generator = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.arange(float(size)), torch.arange(float(size)), indexing="ij")
    height = torch.zeros(size, size)
    for cx, cy, r in (torch.rand(12, 3, generator=generator) * torch.tensor([size, size, size / 6.0])).tolist():
        dx = torch.remainder(xx - cx + size / 2, size) - size / 2
        dy = torch.remainder(yy - cy + size / 2, size) - size / 2
        height = torch.maximum(height, (1.0 - (dx * dx + dy * dy) / (r + 2.0) ** 2).clamp_min(0.0).sqrt())
    with torch.no_grad():
        model.f_u.normal_(generator=generator)
        model.f_u[..., 0] = height
    model.set_height(0.1 * height)
    return model


def test_hist_synthesizes_the_height_on_its_own_with_its_histogram_and_the_features_offsets():
    """A relief model's hist tables keep the height out of the features' PCA (its own 1-D transform): the march
    reads one channel. The synthesized height keeps the exemplar height's histogram (over 200 000 points: its
    percentiles on average within 2% of the range, the CDFs within 0.04) and is read at the features' positions:
    where one lattice sample dominates the blend (weight > 1 - 1e-6) at a texel centre, height and features are
    the exemplar's at that sample's texel (within the inverse tables' error)."""
    model = pebble_model()
    btf = synthesized_btf(model, "hist", seed=3)
    synth = btf.synthesizer
    matrix, _ = synth.output_map()
    c = model.positional_plane().shape[-1]
    assert synth.separate == 1 and torch.equal(matrix[:, -1], torch.eye(c)[-1]) and torch.equal(matrix[-1], torch.eye(c)[-1])
    generator = torch.Generator().manual_seed(8)
    uv = torch.rand(200_000, 2, dtype=torch.float64, generator=generator) * 300.0
    height = synth.channel(uv, -1).double()
    torch.testing.assert_close(height, synth(uv)[:, -1].double(), atol=0, rtol=0)  # the same values as a full fetch
    exemplar = model.height_channel.detach().double().reshape(-1)
    q = torch.linspace(0.01, 0.99, 99, dtype=torch.float64)
    span = float(exemplar.max() - exemplar.min())
    gap = (torch.quantile(height, q) - torch.quantile(exemplar, q)).abs() / span
    # measured: mean 1.1%, median 0.04% of the range; the CDFs 2.3% apart at most (at the edge of the ground's atom)
    assert float(gap.mean()) < 0.02 and float(gap.median()) < 0.005, gap
    values = torch.unique(exemplar)
    cdf = [torch.searchsorted(torch.sort(x).values, values, right=True).double() / len(x) for x in (height, exemplar)]
    assert float((cdf[0] - cdf[1]).abs().max()) < 0.04
    assert float((exemplar == 0).double().mean()) > 0.3  # skewed: the ground is an atom at 0, kept
    # alignment: texel centres whose blend is one sample's; that sample's texel holds the expected values
    size = model.height_channel.shape[0]
    texel = torch.randint(0, 300 * size, (200_000, 2), generator=generator)
    centres = (texel.double() + 0.5) / size
    positions, bary = synth.sample_positions(centres)
    weights = bary ** synth.gamma / (bary ** synth.gamma).sum(-1, keepdim=True)
    top, which = weights.max(-1)
    keep = top > 1 - 1e-6
    assert int(keep.sum()) > 1000
    read = positions[keep].gather(1, which[keep, None, None].expand(-1, 1, 2))[:, 0]  # the sample's position, [0, 1)
    rows, cols = (read[:, 1] * size).floor().long(), (read[:, 0] * size).floor().long()
    plane = model.positional_plane().detach()
    want = plane[rows, cols]
    got = synth(centres[keep])
    tolerance = 0.03 * plane.reshape(-1, c).std(0)  # the inverse tables: ~1% of a channel's spread
    assert bool(((got - want).abs() <= tolerance).all()), ((got - want).abs() / tolerance).max(0).values.tolist()


def test_cli_fits_a_parallax_model_and_rejects_stereo_options_for_other_kinds(tmp_path, capsys):
    from dynbtf.cli.main import main

    out = tmp_path / "p.dbtfm"
    assert main(["fit", "sim:stone?size=16", "-o", str(out), "--repr", "triple-parallax", "--epochs", "1",
                 "--stereo-max-height", "0.1", "--quiet", "--workers", "1"]) == 0
    rep, meta = load_model(out)
    assert rep.kind == "triple-parallax" and meta["provenance"]["height_field"]["options"] == {"max_height": 0.1}
    assert float(rep.height_field().detach().abs().max()) > 0
    assert main(["inspect", str(out), "-o", str(tmp_path / "planes")]) == 0
    assert (tmp_path / "planes" / "height.png").exists()
    capsys.readouterr()
    assert main(["fit", "sim:stone?size=16", "-o", str(tmp_path / "t.dbtfm"), "--stereo-max-height", "0.1",
                 "--repr", "triple"]) == 2
    assert "--stereo-max-height applies to --repr triple-parallax (or auto), not 'triple'" in \
        capsys.readouterr().err
    assert not (tmp_path / "t.dbtfm").exists()


def test_view_coherent_epochs_visit_every_training_pair(tmp_path, monkeypatch):
    """texel_groups = 1: each step's images share a view, and an epoch covers every training pair (and no
    held-out one); the last block of a view is wrapped round, so a pair may come twice."""
    from synthetic_btf import synthetic_btf

    from dynbtf.training import ImageStore

    btf = synthetic_btf(8, thetas=(0.0, 30.0, 60.0), counts=(1, 6, 8))
    requested = []
    original = ImageStore.get

    def spy(self, pairs, texels=None, **options):
        requested.append(np.asarray(pairs).copy())
        return original(self, pairs, texels, **options)

    monkeypatch.setattr(ImageStore, "get", spy)
    config = TrainConfig(epochs=1, images_per_step=4, held_out_fraction=0.1, seed=3, workers=1, monitor_pairs=0,
                         device="cpu", precision="fp32")
    fit(ParallaxTriplePlane(8, 8, seed=3), btf, config, tmp_path / "m.dbtfm", progress=False)
    train, held = held_out_split(btf.n_views, btf.n_lights, 0.1, 3)
    assert all(len(p) == 4 and len(set(p[:, 0])) == 1 for p in requested)
    seen = {tuple(p) for batch in requested for p in batch}
    assert seen == set(map(tuple, train))
    per_view = np.bincount(train[:, 0], minlength=btf.n_views)
    assert len(requested) == int(np.ceil(per_view / 4).sum())
