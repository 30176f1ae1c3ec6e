"""Layered materials (dynbtf.layered): regions, the structure-following boundary, masks, errors."""

import numpy as np
import pytest
import torch

from dynbtf.errors import InputError
from dynbtf.synthesized import synthesized_btf
from dynbtf.layered import ImageMask, LayeredBTF, NoiseMask
from dynbtf.representations.triple_plane import TriplePlane
from dynbtf.synthesis.hash import MASK32


@pytest.fixture(scope="module")
def layers():
    a = synthesized_btf(TriplePlane(16, 16, seed=1), "hist", scale=4.0, seed=3)
    b = synthesized_btf(TriplePlane(16, 16, seed=2), "hist", scale=4.0, seed=4)
    return a, b


def half_plane():
    """Layer 0 for u < 1, layer 1 for u > 1 (a linear ramp across u in [0.5, 1.5]: |grad m| = 1, so the
    signed distance to the contour is exactly u - 1)."""
    return ImageMask(np.array([[0.0, 1.0]]), size=2.0, wrap="clamp")


def directions(n, seed=0):
    rng = np.random.default_rng(seed)
    w = rng.normal(size=(n, 3))
    w[:, 2] = np.abs(w[:, 2]) + 0.3
    return w / np.linalg.norm(w, axis=1, keepdims=True)


def test_layer_height_is_the_rank_among_the_exemplars_texels(layers):
    """Against a brute-force count: the height of a raw value is the share of the exemplar's texels below it (to the
    table's resolution); the exemplar's own texels spread evenly over [0, 1]; beyond its range, 0 and 1."""
    from dynbtf.layered import HEIGHT_TABLE, layer_height_map

    for btf in layers:
        height = layer_height_map(btf)
        plane = btf.model.positional_plane().detach().double().reshape(-1, len(height.weights)).numpy()
        raw = plane @ height.weights
        probes = np.quantile(raw, np.linspace(0.02, 0.98, 49))
        brute = np.array([(raw < x).mean() + 0.5 * (raw == x).mean() for x in probes])
        np.testing.assert_allclose(height(probes), brute, atol=1.5 / len(raw) + 2.0 / HEIGHT_TABLE)
        ranks = height(raw)
        assert abs(ranks.mean() - 0.5) < 0.01 and abs(np.median(ranks) - 0.5) < 0.02
        assert height(raw.min() - 1.0) < 0.01 and height(raw.max() + 1.0) > 0.99
        assert np.all(np.diff(height.table) >= 0) and len(height.table) == HEIGHT_TABLE


def test_away_from_the_boundary_each_region_is_its_layer_exactly(layers):
    a, b = layers
    layered = LayeredBTF([a, b], half_plane(), width=0.1)
    rng = np.random.default_rng(0)
    left = np.stack([rng.uniform(0.0, 0.85, 300), rng.uniform(-5, 5, 300)], 1)
    right = np.stack([rng.uniform(1.15, 2.0, 300), rng.uniform(-5, 5, 300)], 1)
    wv, wl = directions(300, 1), directions(300, 2)
    np.testing.assert_array_equal(layered.eval(left, wv, wl), a.eval(left, wv, wl))
    np.testing.assert_array_equal(layered.eval(right, wv, wl), b.eval(right, wv, wl))
    out = layered.eval(torch.from_numpy(right), torch.from_numpy(wv), torch.from_numpy(wl))
    assert isinstance(out, torch.Tensor) and torch.equal(out, torch.from_numpy(b.eval(right, wv, wl)))


def test_the_boundary_follows_the_heights_within_the_width(layers):
    a, b = layers
    width = 0.1
    layered = LayeredBTF([a, b], half_plane(), width=width)
    u = np.linspace(0.8, 1.2, 81)
    v = np.linspace(0.0, 3.0, 400)
    uv = np.stack(np.meshgrid(u, v, indexing="xy"), -1).reshape(-1, 2)
    weight = layered.weight(uv).reshape(len(v), len(u))
    distance = u - 1.0
    outside = np.abs(distance) >= width
    assert (weight[:, outside & (distance < 0)] == 0).all() and (weight[:, outside & (distance > 0)] == 1).all()
    # inside the band the choice is each point's: layer 1's high parts reach into layer 0's side and back
    crossing = weight[:, np.abs(distance) < width]
    assert 0.05 < crossing.mean() < 0.95
    reach_left = distance[(weight > 0).any(0) & (distance < 0)]
    reach_right = distance[(weight < 1).any(0) & (distance > 0)]
    assert reach_left.size and reach_right.size
    assert -width < reach_left.min() < -0.4 * width and 0.4 * width < reach_right.max() < width
    # not a straight line: along v, the first column showing layer 1 changes from row to row
    first = np.argmax(weight > 0, axis=1)
    assert len(np.unique(first)) > 5
    # the rule itself, against the layers' heights: layer 1 exactly where h1 - h0 + d / width > 0
    band = np.abs(np.tile(distance, len(v))) < width
    heights = layered.heights(torch.from_numpy(uv[band])).numpy()
    expected = heights[:, 1] - heights[:, 0] + (uv[band, 0] - 1.0) / width > 0
    np.testing.assert_array_equal(weight.reshape(-1)[band], expected.astype(float))


def test_swapping_the_layers_and_inverting_the_mask_swaps_the_choice(layers):
    a, b = layers
    image = np.array([[0.0, 1.0]])
    first = LayeredBTF([a, b], ImageMask(image, 2.0, "clamp"), width=0.1)
    second = LayeredBTF([b, a], ImageMask(1.0 - image, 2.0, "clamp"), width=0.1)
    uv = np.stack([np.linspace(0.8, 1.2, 2001), np.full(2001, 0.37)], 1)
    w1, w2 = first.weight(uv), second.weight(uv)
    ties = np.isclose(first.heights(torch.from_numpy(uv)).numpy() @ np.array([1.0, -1.0]) + (uv[:, 0] - 1.0) / 0.1, 0)
    np.testing.assert_array_equal(w1[~ties], 1.0 - w2[~ties])


def test_softness_blends_inside_the_band_only(layers):
    a, b = layers
    layered = LayeredBTF([a, b], half_plane(), width=0.1, softness=0.2)
    uv = np.stack([np.linspace(0.85, 1.15, 301), np.full(301, 1.3)], 1)
    weight = layered.weight(uv)
    assert ((weight > 0) & (weight < 1)).any()
    inside = np.abs(uv[:, 0] - 1.0) < 0.1
    assert ((weight[~inside] == 0) | (weight[~inside] == 1)).all()
    wv, wl = directions(len(uv), 3), directions(len(uv), 4)
    mixed = np.flatnonzero((weight > 0) & (weight < 1))
    expected = (1 - weight[mixed, None]) * a.eval(uv[mixed], wv[mixed], wl[mixed]) + \
        weight[mixed, None] * b.eval(uv[mixed], wv[mixed], wl[mixed])
    np.testing.assert_allclose(layered.eval(uv, wv, wl)[mixed], expected, rtol=1e-5, atol=1e-6)


def test_away_from_the_boundary_only_one_layer_is_evaluated(layers, monkeypatch):
    a, b = layers
    layered = LayeredBTF([a, b], half_plane(), width=0.1)
    counts = {}
    for name, btf in (("a", a), ("b", b)):
        real = btf.eval
        monkeypatch.setattr(btf, "eval", lambda uv, *args, _real=real, _name=name, **kw:
                            counts.__setitem__(_name, counts.get(_name, 0) + len(uv)) or _real(uv, *args, **kw))
    uv = np.stack([np.linspace(0.0, 2.0, 1000), np.zeros(1000)], 1)
    layered.eval(uv, directions(1000), directions(1000, 1))
    band = int((np.abs(uv[:, 0] - 1.0) < 0.1).sum())
    assert counts["a"] + counts["b"] == 1000  # each point from one layer (softness 0)
    assert counts["a"] <= 500 + band and counts["b"] <= 500 + band


def test_image_mask_repeats_exactly_far_from_the_origin_and_its_gradient_is_the_interpolants():
    rng = np.random.default_rng(5)
    mask = ImageMask(rng.random((7, 9)), size=0.5)
    uv = rng.uniform(0, 0.5, (200, 2))
    shift = np.array([2.0 ** 30, -(2.0 ** 28)])  # whole repeats
    far = uv + shift
    np.testing.assert_allclose(mask.value(far), mask.value(far - shift), rtol=0, atol=1e-12)  # the same point
    # uv + shift rounds uv to 2**-22 (float64 at 2**30): values move by that times the slope (18 per uv here)
    np.testing.assert_allclose(mask.value(far), mask.value(uv), rtol=0, atol=2.0 ** -22 * 18 * 2)
    step = 1e-6
    numeric = np.stack([(mask.value(uv + [step, 0]) - mask.value(uv - [step, 0])) / (2 * step),
                        (mask.value(uv + [0, step]) - mask.value(uv - [0, step])) / (2 * step)], -1)
    np.testing.assert_allclose(mask.gradient(uv), numeric, rtol=1e-4, atol=1e-4)


def test_image_mask_is_the_bilinear_interpolant_of_its_texels():
    """Against the interpolant written per point: texel centres at half-texel offsets, repeat wraps the texel
    indices, clamp extends the edge texels."""
    rng = np.random.default_rng(11)
    image = rng.random((5, 7))
    uv = np.concatenate([rng.uniform(-3, 3, (300, 2)), [[0.0, 0.0], [0.999, 0.5], [1.0, 1.0]]])
    for wrap in ("repeat", "clamp"):
        mask = ImageMask(image, size=1.5, wrap=wrap)
        expected, slope = [], []
        for u, v in uv:
            x, y = u / 1.5 * 7 - 0.5, v / 1.5 * 5 - 0.5
            if wrap == "repeat":
                x, y = (u % 1.5) / 1.5 * 7 - 0.5, (v % 1.5) / 1.5 * 5 - 0.5
            i, j = int(np.floor(x)), int(np.floor(y))
            fx, fy = x - i, y - j

            def texel(row, col):
                if wrap == "repeat":
                    return image[row % 5, col % 7]
                return image[min(max(row, 0), 4), min(max(col, 0), 6)]

            a, b, c, d = texel(j, i), texel(j, i + 1), texel(j + 1, i), texel(j + 1, i + 1)
            expected.append(a * (1 - fx) * (1 - fy) + b * fx * (1 - fy) + c * (1 - fx) * fy + d * fx * fy)
            slope.append([((b - a) * (1 - fy) + (d - c) * fy) * 7 / 1.5, ((c - a) * (1 - fx) + (d - b) * fx) * 5 / 1.5])
        value, gradient = mask.value_and_gradient(uv)
        np.testing.assert_allclose(value, expected, rtol=0, atol=1e-14)
        np.testing.assert_allclose(gradient, slope, rtol=0, atol=1e-12)


def reference_noise(u, v, scale, seed):
    """Value noise written out per point with Python integers: lowbias32 of the salted seed, then per coordinate
    its low and high 32-bit words folded in (mix(mix(h ^ low) ^ high)), as dynbtf.synthesis.hash documents."""
    def mix(x):
        x &= MASK32
        x ^= x >> 16
        x = (x * 0x7FEB352D) & MASK32
        x ^= x >> 15
        x = (x * 0x846CA68B) & MASK32
        return x ^ (x >> 16)

    def vertex(i, j):
        h = mix(seed ^ 0x85EBCA6B)
        for coordinate in (i, j):
            word = coordinate & ((1 << 64) - 1)
            h = mix(mix(h ^ (word & MASK32)) ^ (word >> 32))
        return h / MASK32

    x, y = u / scale, v / scale
    i, j = int(np.floor(x)), int(np.floor(y))
    fx, fy = x - i, y - j
    sx, sy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
    top = vertex(i, j) * (1 - sx) + vertex(i + 1, j) * sx
    bottom = vertex(i, j + 1) * (1 - sx) + vertex(i + 1, j + 1) * sx
    return top * (1 - sy) + bottom * sy


def test_noise_mask_is_seeded_value_noise_at_any_distance():
    mask = NoiseMask(scale=0.25, contrast=1.0, seed=7)
    rng = np.random.default_rng(2)
    uv = rng.uniform(-3, 3, (50, 2)) + np.array([[1e9, -3e8]])
    got = mask.value(uv)
    expected = np.array([reference_noise(u, v, 0.25, 7) for u, v in uv])
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-6)
    assert ((got >= 0) & (got <= 1)).all()
    assert not np.allclose(NoiseMask(0.25, 1.0, seed=8).value(uv), got)
    sharp = NoiseMask(scale=0.25, contrast=4.0, seed=7).value(uv)
    np.testing.assert_allclose(sharp, np.clip(0.5 + 4.0 * (expected - 0.5), 0, 1), atol=1e-6)


def test_noise_mask_gradient_matches_finite_differences():
    mask = NoiseMask(scale=0.3, contrast=1.5, seed=1)
    uv = np.random.default_rng(3).uniform(0.01, 0.29, (100, 2))  # inside one cell
    step = 1e-6
    numeric = np.stack([(mask.value(uv + [step, 0]) - mask.value(uv - [step, 0])) / (2 * step),
                        (mask.value(uv + [0, step]) - mask.value(uv - [0, step])) / (2 * step)], -1)
    np.testing.assert_allclose(mask.gradient(uv), numeric, rtol=1e-3, atol=1e-3)


def test_bad_arguments_are_named(layers):
    a, b = layers
    with pytest.raises(InputError, match=r"mask: expected values in \[0, 1\]"):
        ImageMask(np.array([[0.0, 2.0]]))
    with pytest.raises(InputError, match="mask: expected an image of shape"):
        ImageMask(np.zeros((2, 2, 2, 2)))
    with pytest.raises(InputError, match="mask wrap"):
        ImageMask(np.zeros((2, 2)), wrap="mirror")
    with pytest.raises(InputError, match="width"):
        LayeredBTF([a, b], half_plane(), width=0.0)
    with pytest.raises(InputError, match="layers: expected two SynthesizedBTF"):
        LayeredBTF([a], half_plane())
    with pytest.raises(InputError, match="mask: expected an ImageMask"):
        LayeredBTF([a, b], np.zeros((4, 4)))
    with pytest.raises(InputError, match=r"w_view: expected shape \(2, 3\)"):
        LayeredBTF([a, b], half_plane()).eval(np.zeros((2, 2)), np.zeros((3, 3)), np.zeros((2, 3)))
    with pytest.raises(InputError, match="mask seed"):
        NoiseMask(seed=-1)


def test_synth_writes_a_layered_image_whose_halves_are_the_two_materials(tmp_path, monkeypatch, capsys):
    """`dynbtf synth A --layer B --mask M`: with a half-plane mask painted in a PNG, the image's left and right
    columns are A's and B's own synthesis; a bad mask is a one-line error before any work."""
    from dynbtf.cli.main import main
    from dynbtf.io import load_image, save_image
    from dynbtf.representations.model_file import save_model

    monkeypatch.setenv("DYNBTF_COMPILED_CACHE", "off")
    save_model(tmp_path / "a.dbtfm", TriplePlane(16, 16, seed=1))
    save_model(tmp_path / "b.dbtfm", TriplePlane(16, 16, seed=2))
    painted = np.zeros((8, 8, 3))
    painted[:, 4:] = 1.0
    save_image(tmp_path / "mask.png", painted)
    common = ["--method", "hist", "--scale", "4", "--resolution", "32", "--light", "0,0"]
    assert main(["synth", str(tmp_path / "a.dbtfm"), "--layer", str(tmp_path / "b.dbtfm"), "--mask",
                 str(tmp_path / "mask.png"), "--mask-wrap", "clamp", "--width", "0.05", *common,
                 "-o", str(tmp_path / "layered.exr")]) == 0
    for name in ("a", "b"):
        assert main(["synth", str(tmp_path / f"{name}.dbtfm"), *common, "-o", str(tmp_path / f"{name}.exr")]) == 0
    layered, a, b = (load_image(tmp_path / f"{x}.exr") for x in ("layered", "a", "b"))
    np.testing.assert_array_equal(layered[:, :14], a[:, :14])  # 32 px per uv unit: the band is 1.6 px each side
    np.testing.assert_array_equal(layered[:, 18:], b[:, 18:])
    capsys.readouterr()
    assert main(["synth", str(tmp_path / "a.dbtfm"), "--layer", str(tmp_path / "b.dbtfm"), "--mask", "noise:a,b",
                 "-o", str(tmp_path / "x.png")]) == 2
    assert "--mask 'noise:a,b'" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()


def test_eval_of_given_latent_values_equals_eval_that_synthesizes(layers):
    a, _ = layers
    rng = np.random.default_rng(5)
    uv = rng.uniform(-50, 50, (2000, 2))
    wv, wl = directions(2000, 6), directions(2000, 7)
    wv[:7, 2] = -0.2  # below the horizon: zero either way
    wv = wv / np.linalg.norm(wv, axis=1, keepdims=True)
    latent = a.latent(uv)
    assert a.takes_latent and latent.dtype == torch.float32 and latent.shape[0] == 2000
    # features are the latent values through the output map, as the synthesizer answers them
    torch.testing.assert_close(a.synthesizer.features_from_latent(latent), a.features(uv), rtol=0, atol=0)
    np.testing.assert_array_equal(a.eval(uv, wv, wl, latent=latent), a.eval(uv, wv, wl))
    assert np.all(a.eval(uv, wv, wl, latent=latent)[:7] == 0)


def test_latent_values_that_do_not_fit_are_refused(layers):
    a, _ = layers
    uv = np.zeros((4, 2))
    w = directions(4)
    latent = a.latent(uv)
    with pytest.raises(InputError, match=r"latent: expected float32 values of shape \(4, "):
        a.eval(uv, w, w, latent=latent[:3])
    with pytest.raises(InputError, match="latent: expected float32"):
        a.eval(uv, w, w, latent=latent.double())
    with pytest.raises(InputError, match="latent: given for point queries only"):
        a.eval(uv, w, w, 0.01, latent=latent)


def test_band_points_are_synthesized_once_per_layer(layers, monkeypatch):
    a, b = layers
    layered = LayeredBTF([a, b], half_plane(), width=0.1)
    rng = np.random.default_rng(8)
    band = np.stack([rng.uniform(0.92, 1.08, 500), rng.uniform(-5, 5, 500)], 1)
    wv, wl = directions(500, 9), directions(500, 10)
    expected = layered.eval(band, wv, wl)
    calls = []
    for layer in (a, b):
        original = layer.synthesizer.latent
        monkeypatch.setattr(layer.synthesizer, "latent",
                            lambda uv, *args, _f=original, **kw: (calls.append(len(uv)), _f(uv, *args, **kw))[1])
    np.testing.assert_array_equal(layered.eval(band, wv, wl), expected)
    assert sum(calls) == 2 * 500  # each layer once per band point: for the height, and its colour reused
    # and the colour is each point's layer's own
    choice = layered.weight(band) > 0.5
    np.testing.assert_array_equal(expected[~choice], a.eval(band[~choice], wv[~choice], wl[~choice]))
    np.testing.assert_array_equal(expected[choice], b.eval(band[choice], wv[choice], wl[choice]))


# ---------------------------------------------------------------- footprints: the share of each footprint
def test_footprint_weight_is_the_point_weight_within_a_texel_and_the_covered_share_over_many(layers):
    """Against brute force: layer 1's share of a footprint is the mean of the point weights over the footprint's
    square; the footprint weight gets it (over many centres), and is closer to each centre's share than the
    point weight at its centre (the choice a footprint query made before: a distant boundary aliased)."""
    a, b = layers
    width = 0.1
    layered = LayeredBTF([a, b], half_plane(), width=width)
    rng = np.random.default_rng(5)
    centres = np.stack([1.0 + rng.uniform(-0.15, 0.15, 300), rng.uniform(-20, 20, 300)], 1)
    # within a texel (1/64 uv): the point weight, bit for bit
    np.testing.assert_array_equal(layered.weight(centres, footprint=0.2 / 64), layered.weight(centres))
    side = 0.1  # 6.4 texels of the 16 x 16 exemplars repeated 4 times per uv
    grid = (np.arange(24) + 0.5) / 24 - 0.5
    offsets = np.stack(np.meshgrid(grid, grid), -1).reshape(-1, 2) * side
    brute = layered.weight((centres[:, None, :] + offsets[None]).reshape(-1, 2)).reshape(len(centres), -1).mean(1)
    ours = layered.weight(centres, footprint=side)
    at_centre = layered.weight(centres)
    assert abs(ours.mean() - brute.mean()) < 0.02  # the expectation over many footprints
    for near in (np.abs(centres[:, 0] - 1.0) < 0.05, np.abs(centres[:, 0] - 1.0) >= 0.05):  # near and at the edges
        assert abs(ours[near].mean() - brute[near].mean()) < 0.04
    assert np.abs(ours - brute).mean() < 0.5 * np.abs(at_centre - brute).mean()
    assert ((ours > 0) & (ours < 1)).mean() > 0.5  # a transition, not a choice
    # far from the contour (beyond the band and half the footprint) each region is its layer
    far = np.stack([np.array([0.5, 1.5]), np.array([0.3, 0.3])], 1)
    np.testing.assert_array_equal(layered.weight(far, footprint=side), [0.0, 1.0])


def test_footprint_weight_with_softness_is_the_ramp_averaged_over_the_footprint():
    """:func:`area_weight` against a brute-force average of the point rule over independent uniform heights and the
    footprint's distances, with and without softness."""
    from dynbtf.layered import area_weight, point_weight

    rng = np.random.default_rng(6)
    h = rng.random((2, 400_000))
    for softness in (0.0, 0.3):
        for distance, side in ((-0.07, 0.02), (0.0, 0.3), (0.04, 0.0), (0.12, 0.05)):
            d = distance + (rng.random(h.shape[1]) - 0.5) * side
            brute = point_weight(h[1] - h[0] + d / 0.1, softness).mean()
            ours = area_weight(np.array([distance]), 0.1, softness, np.array([side]))[0]
            assert abs(ours - brute) < 4e-3, (softness, distance, side, ours, brute)


@pytest.mark.filterwarnings("ignore:footprint queries of a material compiled without footprint decoders")
def test_footprint_eval_blends_the_layers_footprint_answers_by_the_footprint_weight(layers):
    a, b = layers
    layered = LayeredBTF([a, b], half_plane(), width=0.1)
    uv = np.stack([np.linspace(0.85, 1.15, 61), np.full(61, 2.7)], 1)
    footprint = np.full(61, 0.08)
    wv, wl = directions(61, 7), directions(61, 8)
    weight = layered.weight(uv, footprint)
    assert ((weight > 0) & (weight < 1)).any() and (weight == 0).any() and (weight == 1).any()
    expected = (1 - weight[:, None]) * a.eval(uv, wv, wl, footprint) + weight[:, None] * b.eval(uv, wv, wl, footprint)
    np.testing.assert_allclose(layered.eval(uv, wv, wl, footprint), expected, rtol=1e-5, atol=1e-6)
    with pytest.raises(InputError, match="footprint"):
        layered.eval(uv, wv, wl, np.full(61, -1.0))
