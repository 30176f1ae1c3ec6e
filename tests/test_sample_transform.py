"""Lattice blending's quarter-turned and scaled samples (dynbtf.synthesis.sample_transform), against brute force."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dynbtf.errors import InputError
from dynbtf.synthesis.hash import hash_vertex, mix32, vertex_offsets
from dynbtf.synthesis.lattice import triangle_lattice, vertex_uv
from dynbtf.synthesis.registry import make_synthesizer
from dynbtf.synthesis.sample_transform import PIVOT_SHIFT, SCALE_STREAM, inverse_scales, quarter_turns, scale_log


def _bilinear(plane: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Periodic bilinear read of ``plane (H, W, C)`` at texel positions (texel ``[i, j]`` centred at ``(j + .5, i + .5)``),
    written out texel by texel (float64)."""
    h, w, _ = plane.shape
    px, py = x - 0.5, y - 0.5
    x0, y0 = np.floor(px), np.floor(py)
    tx, ty = (px - x0)[:, None], (py - y0)[:, None]
    c0, r0 = x0.astype(np.int64) % w, y0.astype(np.int64) % h
    c1, r1 = (c0 + 1) % w, (r0 + 1) % h
    return ((1 - tx) * (1 - ty) * plane[r0, c0] + tx * (1 - ty) * plane[r0, c1] + (1 - tx) * ty * plane[r1, c0]
            + tx * ty * plane[r1, c1])


def _brute_force_linear(exemplar: torch.Tensor, uv: torch.Tensor, seed: int, rotation: bool = True,
                        jitter: float = 0.0):
    """``linear`` blending with turned and scaled samples, from the definition: sample ``k`` reads the exemplar at
    ``c_k + A_k (q - c_k) / f_k + o_k`` (texels; ``c_k`` the vertex's pivot, a texel centre next to it, ``o_k`` its
    offset, ``q`` the query, ``A_k`` its quarter turns, ``f_k = (1 + jitter)^(2 r - 1)`` its scale, ``r`` the top 24
    bits of its hash's scale stream), weighted by the barycentrics."""
    plane = exemplar.double().numpy()
    h, w, _ = plane.shape
    vertices, bary = triangle_lattice(uv)
    ox, oy = vertex_offsets(vertices[..., 0], vertices[..., 1], seed, w, h)
    hashes = hash_vertex(vertices[..., 0], vertices[..., 1], seed)
    angle = quarter_turns(hashes).numpy() * (np.pi / 2) if rotation else np.zeros(hashes.shape)
    r = (mix32(hashes ^ SCALE_STREAM) >> 8).numpy() / 2.0 ** 24
    factor = (1.0 + jitter) ** (2.0 * r - 1.0)
    centre = np.floor(vertex_uv(vertices).numpy() * np.array([w, h]) + PIVOT_SHIFT) + 0.5  # (N, 3, 2) texels
    q = uv.numpy()[:, None, :] * np.array([w, h])
    d = q - centre
    c, s = np.round(np.cos(angle)) / factor, np.round(np.sin(angle)) / factor
    x = centre[..., 0] + ox.numpy() + c * d[..., 0] - s * d[..., 1]
    y = centre[..., 1] + oy.numpy() + s * d[..., 0] + c * d[..., 1]
    out = 0.0
    for k in range(3):
        out = out + bary[:, k:k + 1].numpy() * _bilinear(plane, x[:, k], y[:, k])
    return out


@pytest.fixture(scope="module")
def exemplar():
    torch.manual_seed(0)
    return torch.randn(40, 48, 5)


def test_turned_samples_read_where_the_definition_says(exemplar):
    """The fused kernel and the torch reference of ``linear`` = the brute-force definition (float32 blend)."""
    uv = torch.rand(4000, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) * 6.0 - 2.0
    synth = make_synthesizer("linear", exemplar, seed=7, tileable=False, rotation=True)
    expected = _brute_force_linear(exemplar, uv, 7)
    # float32 blends, and the reference's float32 read positions (~1e-6 texel on 48 texels)
    np.testing.assert_allclose(synth.latent(uv).numpy(), expected, atol=5e-5)
    np.testing.assert_allclose(synth.reference_latent(uv).numpy(), expected, atol=5e-5)
    plain = make_synthesizer("linear", exemplar, seed=7, tileable=False)
    assert np.abs(plain.latent(uv).numpy() - expected).max() > 0.5  # the turns change what is read


def test_a_texel_centre_reads_whole_texels(exemplar):
    """At every texel centre, near the origin and at 1e9 repeats, each turned sample reads exactly one exemplar
    texel (its read point is a texel centre): quarter turns resample nothing."""
    h, w, _ = exemplar.shape
    centres = (torch.stack(torch.meshgrid(torch.arange(3 * w), torch.arange(3 * h), indexing="xy"), -1)
               .reshape(-1, 2).double() + 0.5) / torch.tensor([w, h], dtype=torch.float64)
    synth = make_synthesizer("linear", exemplar, seed=2, tileable=False, rotation=True)
    # (at 1e9 repeats float64 holds uv to 1.2e-7 repeats: 6e-6 texel here)
    for origin, tolerance in ((0.0, 1e-9), (1e9, 1e-5)):
        positions, _ = synth.sample_positions(centres + origin)
        texels = positions * torch.tensor([w, h], dtype=torch.float64) - 0.5
        assert float((texels - torch.round(texels)).abs().max()) < tolerance


@pytest.mark.parametrize("rotation, jitter", [(False, 0.3), (True, 1.0)])
def test_scaled_samples_read_where_the_definition_says(exemplar, rotation, jitter):
    """Scaled (and turned) samples: the fused kernel and the torch reference of ``linear`` = the brute-force
    definition, near the origin and at 1e9 repeats."""
    uv = torch.rand(4000, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(4)) * 6.0 - 2.0
    synth = make_synthesizer("linear", exemplar, seed=5, tileable=False, rotation=rotation, scale_jitter=jitter)
    expected = _brute_force_linear(exemplar, uv, 5, rotation, jitter)
    np.testing.assert_allclose(synth.latent(uv).numpy(), expected, atol=5e-5)
    np.testing.assert_allclose(synth.reference_latent(uv).numpy(), expected, atol=5e-5)
    unscaled = _brute_force_linear(exemplar, uv, 5, rotation, 0.0)
    assert np.abs(synth.latent(uv).numpy() - unscaled).max() > 0.5  # the scales change what is read
    far = uv + torch.tensor([1e9, -3e8], dtype=torch.float64)
    # (at 1e9 repeats float64 holds uv to 1.2e-7 repeats: 6e-6 texel here, times the blend's slope)
    np.testing.assert_allclose(synth.latent(far).numpy(), _brute_force_linear(exemplar, far, 5, rotation, jitter),
                               atol=2e-4)


def test_scale_factors_are_log_uniform_and_the_numba_twin_draws_them():
    """``1 / f`` over many hashes: log-uniform in ``[1 / (1 + j), 1 + j]`` (its quartiles), the compiled twin's
    to float64 rounding, and exactly 1 with no jitter."""
    import numba

    from dynbtf.synthesis.kernels import jit_inverse_scales

    @numba.njit
    def draw(h, log_range):
        out = np.empty(h.shape[0], dtype=np.float64)
        for i in range(h.shape[0]):
            out[i] = jit_inverse_scales(h[i], log_range)
        return out

    h = torch.randint(0, 1 << 32, (40000,), dtype=torch.int64, generator=torch.Generator().manual_seed(1))
    inverse = inverse_scales(h, scale_log(0.5))
    np.testing.assert_allclose(inverse.numpy(), draw(h.numpy(), scale_log(0.5)), rtol=1e-15)  # (exp's last bit)
    log_f = -np.log(inverse.numpy()) / np.log(1.5)  # uniform in [-1, 1]
    assert log_f.min() >= -1.0 and log_f.max() <= 1.0
    np.testing.assert_allclose(np.quantile(log_f, [0.25, 0.5, 0.75]), [-0.5, 0.0, 0.5], atol=0.02)
    assert torch.equal(inverse_scales(h, 0.0), torch.ones(h.shape, dtype=torch.float64))


@pytest.mark.parametrize("method, rotation, jitter", [("linear", True, 0.0), ("hist", True, 0.0), ("hex", True, 0.0),
                                                      ("hist", False, 0.5), ("hex", True, 0.5)])
def test_kernels_equal_the_reference_far_from_the_origin(exemplar, method, rotation, jitter):
    """Point and footprint kernels = the torch reference, at 1e9 repeats as near the origin."""
    g = torch.Generator().manual_seed(2)
    uv = torch.rand(3000, 2, dtype=torch.float64, generator=g) * 5.0
    uv[1500:] += torch.tensor([1e9, -3e8], dtype=torch.float64)
    synth = make_synthesizer(method, exemplar, seed=4, tileable=False, rotation=rotation, scale_jitter=jitter)
    reference = synth.reference_latent(uv)
    tolerance = 2e-2 if method == "hist" else 1e-4  # hist: the kernel's tabulated inverse (its own test bounds it)
    np.testing.assert_allclose(synth.latent(uv).numpy(), reference.numpy(), atol=tolerance)
    footprint = torch.full((uv.shape[0],), 3.0, dtype=torch.float64)
    fast = synth.filtered_latent(uv, footprint)
    synth.fast = False
    np.testing.assert_allclose(fast.numpy(), synth.filtered_latent(uv, footprint).numpy(), atol=tolerance)


def test_off_is_the_plain_method_bit_for_bit(exemplar):
    uv = torch.rand(2000, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(3)) * 9.0
    plain = make_synthesizer("hist", exemplar, seed=1)
    off = make_synthesizer("hist", exemplar, seed=1, rotation=False, scale_jitter=0.0)
    assert torch.equal(plain.latent(uv), off.latent(uv))
    assert off.frame_rotation(uv) is None
    scaled = make_synthesizer("hist", exemplar, seed=1, scale_jitter=0.5)
    assert scaled.frame_rotation(uv) is None  # a scale leaves the directions as they are
    turned = make_synthesizer("hist", exemplar, seed=1, rotation=True)
    both = make_synthesizer("hist", exemplar, seed=1, rotation=True, scale_jitter=0.5)
    assert torch.equal(turned.frame_rotation(uv), both.frame_rotation(uv))


def test_numba_twin_draws_the_same_turns():
    from dynbtf.synthesis.kernels import jit_quarter_turns

    import numba

    @numba.njit
    def draw(h):
        turns = np.empty(h.shape[0], dtype=np.int64)
        for i in range(h.shape[0]):
            turns[i] = jit_quarter_turns(h[i])
        return turns

    h = torch.randint(0, 1 << 32, (20000,), dtype=torch.int64, generator=torch.Generator().manual_seed(0))
    turns = quarter_turns(h)
    np.testing.assert_array_equal(turns.numpy(), draw(h.numpy()))
    counts = np.bincount(turns.numpy(), minlength=4)
    assert counts.shape == (4,) and counts.min() > 4700  # each of the four turns about a quarter of the time


def _orientation_coherence(image: np.ndarray) -> float:
    """Structure-tensor coherence ``(l1 - l2) / (l1 + l2)`` of a grey image's gradients, summed over it: 1 for
    one orientation everywhere, near 0 for every orientation."""
    gy, gx = np.gradient(image)
    jxx, jyy, jxy = (gx * gx).sum(), (gy * gy).sum(), (gx * gy).sum()
    root = math.sqrt((jxx - jyy) ** 2 + 4 * jxy ** 2)
    return root / (jxx + jyy)


def test_rotation_turns_an_oriented_pattern():
    """Stripes along one axis keep one orientation under hist; turned samples spread it over every angle."""
    y, x = np.mgrid[0:64, 0:64]
    stripes = np.sin(2 * np.pi * x / 8.0)[..., None] + 0.05 * np.random.default_rng(0).normal(size=(64, 64, 1))
    exemplar = torch.from_numpy(np.concatenate([stripes, stripes ** 2], -1)).float()
    grid = (np.stack(np.meshgrid(np.arange(256), np.arange(256)), -1).reshape(-1, 2) + 0.5) / 64.0 + 5.0
    uv = torch.from_numpy(grid)
    coherence = {}
    for rotation in (False, True):
        coherences = []
        for seed in range(3):
            synth = make_synthesizer("hist", exemplar, seed=seed, tileable=False, rotation=rotation)
            image = synth.latent(uv).numpy()[:, 0].reshape(256, 256)
            coherences.append(_orientation_coherence(image))
        coherence[rotation] = max(coherences) if rotation else min(coherences)
    assert coherence[False] > 0.75  # (measured 0.81-0.82 over the seeds; the blends' transitions take the rest)
    assert coherence[True] < 0.2


def test_hist_frame_follows_the_dominant_sample(exemplar):
    """Where one sample has nearly all of hist's weight, the query's frame angle is that sample's angle."""
    uv = torch.rand(20000, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(5)) * 4.0
    synth = make_synthesizer("hist", exemplar, seed=2, rotation=True)
    vertices, bary = triangle_lattice(uv)
    angle = quarter_turns(hash_vertex(vertices[..., 0], vertices[..., 1], 2)).double() * (math.pi / 2)
    weights = bary ** 7 / (bary ** 7).sum(-1, keepdim=True)
    top, k = weights.max(-1)
    dominant = top > 0.999
    assert int(dominant.sum()) > 1000
    frame = synth.frame_rotation(uv)[dominant]
    own = angle[dominant, k[dominant]]
    np.testing.assert_allclose(frame.numpy(), torch.stack([torch.cos(own), torch.sin(own)], -1).numpy(), atol=2e-3)


def test_synthesized_btf_turns_the_directions_into_the_frame():
    """eval = the decoder at the synthesized latent with view and light turned by the frame angle, and differs
    from decoding with the directions as given."""
    from dynbtf.conventions import spherical_to_direction
    from dynbtf.representations.triple_plane import TriplePlane
    from dynbtf.synthesized import synthesized_btf

    model = TriplePlane(24, 20, positional_channels=6, angular_channels=3, hidden=12, seed=5)
    btf = synthesized_btf(model, "hist", seed=3, rotation=True)
    rng = np.random.default_rng(0)
    n = 3000
    uv = torch.from_numpy(rng.random((n, 2)) * 10.0)
    wv = torch.from_numpy(spherical_to_direction(rng.random(n) * 70, rng.random(n) * 360)).float()
    wl = torch.from_numpy(spherical_to_direction(rng.random(n) * 70, rng.random(n) * 360)).float()
    got = btf.eval(uv, wv, wl)
    frame = btf.synthesizer.frame_rotation(uv).float()
    c, s = frame[:, :1], frame[:, 1:]
    np.testing.assert_allclose((c * c + s * s).numpy(), 1.0, atol=1e-6)

    def turned(w):
        return torch.cat([c * w[:, :1] - s * w[:, 1:2], s * w[:, :1] + c * w[:, 1:2], w[:, 2:]], 1)

    latent = btf.latent(uv)
    np.testing.assert_allclose(got.numpy(), btf.decode_path.decode(latent, turned(wv), turned(wl)).numpy(), atol=1e-5)
    assert (got - btf.decode_path.decode(latent, wv, wl)).abs().max() > 1e-3


@pytest.mark.parametrize("value", [-5.0, 2, "yes", None])
def test_bad_values_are_refused_by_name(exemplar, value):
    with pytest.raises(InputError, match=r"rotation: expected true or false \(each sample turned by a random quarter"):
        make_synthesizer("hist", exemplar, rotation=value)


@pytest.mark.parametrize("value", [-0.1, 1.5, math.nan, "big", True])
def test_bad_scale_jitters_are_refused_by_name(exemplar, value):
    with pytest.raises(InputError, match=r"scale_jitter: expected a scale jitter in \[0, 1\] \(each sample magnified"):
        make_synthesizer("hex", exemplar, scale_jitter=value)


def test_guidance_refuses_turned_samples(exemplar):
    from dynbtf.synthesis.guided_blending import LabelField

    labels = torch.zeros(40, 48, dtype=torch.long)
    with pytest.raises(InputError, match="rotation: the guided methods read their candidates' content unturned"):
        make_synthesizer("guided", exemplar, labels=labels, target=LabelField([[0]]), rotation=True)
    with pytest.raises(InputError, match="scale_jitter: the guided methods read their candidates' content unturned "
                                         "and unscaled"):
        make_synthesizer("guided", exemplar, labels=labels, target=LabelField([[0]]), scale_jitter=0.2)


def test_cli_synth_takes_rotation(tmp_path, capsys):
    from dynbtf.cli.main import main
    from dynbtf.io import load_image
    from dynbtf.representations.model_file import save_model
    from dynbtf.representations.triple_plane import TriplePlane

    save_model(tmp_path / "m.dbtfm", TriplePlane(24, 24, seed=1))
    common = [str(tmp_path / "m.dbtfm"), "--method", "hist", "--scale", "4", "--resolution", "48"]
    assert main(["synth", *common, "-o", str(tmp_path / "plain.exr")]) == 0
    assert main(["synth", *common, "--rotation", "-o", str(tmp_path / "t.exr")]) == 0
    assert main(["synth", *common, "--scale-jitter", "0.3", "-o", str(tmp_path / "s.exr")]) == 0
    plain, turned = load_image(tmp_path / "plain.exr"), load_image(tmp_path / "t.exr")
    scaled = load_image(tmp_path / "s.exr")
    assert np.isfinite(turned).all() and np.abs(turned - plain).max() > 1e-3
    assert np.isfinite(scaled).all() and np.abs(scaled - plain).max() > 1e-3
    capsys.readouterr()
    for extra, message in ((["--method", "tile", "--rotation"], "--rotation: turning the samples is for hex, hist, "
                                                                "linear; give it with --method hex"),
                           (["--method", "struct", "--scale-jitter", "0.2"], "--scale-jitter: scaling the samples is "
                                                                             "for hex, hist, linear"),
                           (["--method", "hist", "--scale-jitter", "3"], "--scale-jitter: expected a scale jitter in "
                                                                         "[0, 1]"),
                           (["--method", "hist", "--rotation", "--layer", str(tmp_path / "m.dbtfm")],
                            "--rotation: turning the samples is for hex")):
        assert main(["synth", str(tmp_path / "m.dbtfm"), *extra, "-o", str(tmp_path / "x.png")]) == 2
        assert message in capsys.readouterr().err
        assert not (tmp_path / "x.png").exists()


def test_cli_export_turns_the_lattice_methods(tmp_path, capsys):
    """``dynbtf export --rotation`` writes the lattice methods' turns into the manifest, and refuses where no
    exported method takes them."""
    import json

    from dynbtf.cli.main import main
    from dynbtf.representations.model_file import save_model
    from dynbtf.representations.triple_plane import TriplePlane

    save_model(tmp_path / "m.dbtfm", TriplePlane(24, 24, seed=1))
    out = tmp_path / "web"
    assert main(["export", str(tmp_path / "m.dbtfm"), "-o", str(out), "--method", "hist", "--method", "tile",
                 "--rotation", "--scale-jitter", "0.25", "--no-viewer"]) == 0
    manifest = json.loads((out / "manifest.json").read_text())
    methods = manifest["methods"]
    assert methods["hist"]["rotation"] is True and methods["hist"]["frame_exponent"] == 7.0
    assert methods["hist"]["scale_log"] == pytest.approx(math.log(1.25), rel=1e-12)
    assert not methods["tile"].get("rotation")
    capsys.readouterr()
    assert main(["export", str(tmp_path / "m.dbtfm"), "-o", str(tmp_path / "x"), "--method", "tile",
                 "--rotation"]) == 2
    assert ("--rotation: turning the samples is for hex, hist, linear; export one of them with --method (without "
            "--layer or --target), not ['tile']") in capsys.readouterr().err


def test_cli_compile_keeps_the_turns_and_synth_uses_them(tmp_path, capsys):
    """``dynbtf compile --rotation --scale-jitter`` stores the turns and scales in the material, ``--brightness
    --tint`` struct's variation; ``synth`` of the .dbtfc draws them (the image equals synth of the model file with
    the same options), and compile refuses each for a method without it, or a value out of range."""
    from dynbtf.cli.main import main
    from dynbtf.io import load_image
    from dynbtf.representations.model_file import save_model
    from dynbtf.representations.triple_plane import TriplePlane

    save_model(tmp_path / "m.dbtfm", TriplePlane(24, 24, seed=1))
    assert main(["compile", str(tmp_path / "m.dbtfm"), "--method", "hex", "--rotation", "--scale-jitter", "0.4",
                 "--no-footprints", "-o", str(tmp_path / "m.dbtfc")]) == 0
    common = ["--scale", "4", "--resolution", "32"]
    assert main(["synth", str(tmp_path / "m.dbtfc"), *common, "-o", str(tmp_path / "a.exr")]) == 0
    assert main(["synth", str(tmp_path / "m.dbtfm"), "--method", "hex", "--rotation", "--scale-jitter", "0.4",
                 *common, "-o", str(tmp_path / "b.exr")]) == 0
    np.testing.assert_array_equal(load_image(tmp_path / "a.exr"), load_image(tmp_path / "b.exr"))
    # struct's per-element variation is compiled in as well
    variation = ["--brightness", "0.3", "--tint", "0.1"]
    assert main(["compile", str(tmp_path / "m.dbtfm"), "--method", "struct", *variation, "--no-footprints", "-o",
                 str(tmp_path / "s.dbtfc")]) == 0
    assert main(["synth", str(tmp_path / "s.dbtfc"), *common, "-o", str(tmp_path / "c.exr")]) == 0
    assert main(["synth", str(tmp_path / "m.dbtfm"), "--method", "struct", *variation, *common, "-o",
                 str(tmp_path / "d.exr")]) == 0
    assert main(["synth", str(tmp_path / "m.dbtfm"), "--method", "struct", *common, "-o", str(tmp_path / "e.exr")]) == 0
    np.testing.assert_array_equal(load_image(tmp_path / "c.exr"), load_image(tmp_path / "d.exr"))
    assert np.abs(load_image(tmp_path / "c.exr") - load_image(tmp_path / "e.exr")).max() > 1e-3
    capsys.readouterr()
    assert main(["compile", str(tmp_path / "m.dbtfm"), "--method", "struct", "--rotation"]) == 2
    assert "--rotation: turning the samples is for hex, hist, linear" in capsys.readouterr().err
    assert main(["compile", str(tmp_path / "m.dbtfm"), "--method", "hist", "--brightness", "0.2"]) == 2
    assert "--brightness: per-element variation is for struct; give it with --method struct" in capsys.readouterr().err
    assert main(["compile", str(tmp_path / "m.dbtfm"), "--method", "hex", "--scale-jitter", "-1"]) == 2
    assert "--scale-jitter: expected a scale jitter in [0, 1]" in capsys.readouterr().err


def test_scale_jitter_warns_for_a_model_fitted_without_the_subtexel_term(tmp_path, capsys):
    """A model file whose training record has no sub-texel term: ``synthesized_btf(..., scale_jitter=j)`` and
    ``dynbtf synth --scale-jitter`` warn, naming the file; with the term, or without a training record, they do
    not."""
    from dynbtf.cli.main import main
    from dynbtf.representations.model_file import save_model
    from dynbtf.representations.triple_plane import TriplePlane
    from dynbtf.synthesized import synthesized_btf

    model = TriplePlane(16, 16, seed=2)
    without, with_term, plain = tmp_path / "without.dbtfm", tmp_path / "with.dbtfm", tmp_path / "plain.dbtfm"
    save_model(without, model, {"training": {"subtexel": 0.0}})
    save_model(with_term, model, {"training": {"subtexel": 0.25}})
    save_model(plain, model)
    with pytest.warns(UserWarning, match=r"scale_jitter: .*without\.dbtfm was fitted without the sub-texel term"):
        synthesized_btf(without, "hist", scale_jitter=0.3)
    for path in (with_term, plain):
        synthesized_btf(path, "hist", scale_jitter=0.3)  # (warnings are errors in this suite)
    synthesized_btf(without, "hist")  # no scales, no warning
    with pytest.warns(UserWarning, match="fitted without the sub-texel term"):
        assert main(["synth", str(without), "--method", "hist", "--scale-jitter", "0.2", "--resolution", "16",
                     "-o", str(tmp_path / "s.png")]) == 0
