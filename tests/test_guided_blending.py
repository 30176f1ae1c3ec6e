"""Exemplar guidance (dynbtf.synthesis.guided_blending): labels, the target's share, hist where unguided, errors."""

import numpy as np
import pytest
import torch

from dynbtf.errors import InputError
from dynbtf.synthesis.guided_blending import (GuidedBlending, GuidedCellQuilting, GuidedHexTiling, LabelField,
                                             exemplar_labels, source_labels)
from dynbtf.synthesis.cell_quilting import CellQuilting
from dynbtf.synthesis.histogram_blending import HistogramBlending


def two_content_plane(size=32, seed=0):
    """Channel 0 is +1 on the texels labelled 1 (a checkerboard of 4 x 4 blocks) and -1 elsewhere, plus noise."""
    g = torch.Generator().manual_seed(seed)
    rows, cols = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    labels = ((rows // 4 + cols // 4) % 2).long()
    plane = 0.2 * torch.randn(size, size, 4, generator=g)
    plane[..., 0] += 2.0 * labels - 1.0
    return plane, labels


def test_kmeans_labels_find_the_two_contents_and_are_numbered_by_order_by():
    plane, labels = two_content_plane()
    found = exemplar_labels(plane, 2, seed=3)
    assert np.array_equal(found, labels.numpy())  # channel 0's class means: -1 then +1
    reversed_order = exemplar_labels(plane, 2, seed=3, order_by=-plane[..., 0])
    assert np.array_equal(reversed_order, 1 - labels.numpy())
    assert np.array_equal(exemplar_labels(plane, 3, seed=5), exemplar_labels(plane, 3, seed=5))  # seeded


@pytest.mark.parametrize("target_label", [0, 1])
def test_points_show_content_of_their_target_label(target_label):
    plane, labels = two_content_plane()
    synth = GuidedBlending(plane, 7, labels=labels, target=LabelField([[target_label]]), tileable=False)
    rng = np.random.default_rng(0)
    for offset in (0.0, 1e9):  # near the origin and far from it
        uv = torch.from_numpy(rng.uniform(0, 20, (4000, 2)) + offset)
        values = synth(uv)[:, 0].numpy()  # the content itself: +1 where label 1, -1 where label 0
        sign = 1.0 if target_label == 1 else -1.0
        assert np.mean(sign * values > 0) >= 0.95
        assert float((source_labels(synth, uv) == target_label).float().mean()) >= 0.95


def test_a_target_field_steers_each_region():
    plane, labels = two_content_plane()
    target = LabelField(np.array([[0, 1]]), size=4.0, wrap="repeat")  # u mod 4 < 2: label 0, else 1
    synth = GuidedBlending(plane, 1, labels=labels, target=target, tileable=False)
    uv = torch.from_numpy(np.random.default_rng(1).uniform(-50, 50, (6000, 2)))
    expected = (torch.remainder(uv[:, 0], 4.0) >= 2.0).long()
    assert torch.equal(target.labels(uv), expected)
    agree = (synth(uv)[:, 0] > 0).long() == expected
    assert float(agree.float().mean()) >= 0.95


def test_where_hists_own_offsets_match_guided_is_hist():
    plane, _ = two_content_plane()
    uv = torch.from_numpy(np.random.default_rng(2).uniform(-30, 30, (3000, 2)))
    hist = HistogramBlending(plane, 4, tileable=False)
    guided = GuidedBlending(plane, 4, labels=torch.zeros(32, 32, dtype=torch.long), target=LabelField([[0]]),
                            tileable=False)
    assert torch.equal(guided.reference_latent(uv), hist.reference_latent(uv))
    assert torch.equal(guided.latent(uv), hist.latent(uv))  # the fused kernels too


@pytest.mark.parametrize("softness", [0.0, 0.4])
def test_the_fused_kernel_chooses_what_the_torch_path_chooses(softness):
    """The numba kernel's guided search against the torch reference path: the same offsets (a different choice
    would move values by the contents' difference, ~2), the values within the inverse table's error."""
    plane, labels = two_content_plane()
    target = LabelField(np.array([[0, 1], [1, 0]]), size=3.0)
    synth = GuidedBlending(plane, 7, labels=labels, target=target, softness=softness, tileable=False)
    uv = torch.from_numpy(np.random.default_rng(6).uniform(-40, 40, (20000, 2)))
    uv[:100] += 1e12  # far from the origin too
    fast, reference = synth.latent(uv), synth.reference_latent(uv)
    assert float((fast - reference).abs().max()) < 0.05
    assert float((fast - reference).abs().mean()) < 1e-3


def test_softness_one_keeps_hists_weights_and_answers_are_per_point():
    plane, labels = two_content_plane()
    synth = GuidedBlending(plane, 2, labels=labels, target=LabelField([[1]]), softness=1.0, tileable=False)
    uv = torch.from_numpy(np.random.default_rng(3).uniform(0, 10, (2000, 2)))
    _, bary, matched = synth.guided_positions(uv)
    assert torch.equal(synth.steered_barycentrics(bary, matched), bary)
    order = torch.randperm(2000, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(synth(uv[order]), synth(uv)[order], rtol=0, atol=0)  # a function of the point


def test_bad_guidance_is_named():
    plane, labels = two_content_plane()
    field = LabelField([[1]])
    with pytest.raises(InputError, match=r"labels: expected the exemplar's shape \(32, 32\)"):
        GuidedBlending(plane, labels=labels[:5], target=field)
    with pytest.raises(InputError, match="labels: expected non-negative integer labels"):
        GuidedBlending(plane, labels=labels.float(), target=field)
    with pytest.raises(InputError, match="target: expected a LabelField"):
        GuidedBlending(plane, labels=labels, target=[[1]])
    with pytest.raises(InputError, match="softness: expected a weight factor in"):
        GuidedBlending(plane, labels=labels, target=field, softness=2.0)
    with pytest.raises(InputError, match="candidates: expected at least 1"):
        GuidedBlending(plane, labels=labels, target=field, candidates=0)
    with pytest.raises(InputError, match="target: expected labels >= 0"):
        LabelField([[-1, 0]])
    with pytest.raises(InputError, match="classes: expected 2 to"):
        exemplar_labels(plane, 1)


def test_guided_btf_puts_the_dark_class_where_the_target_is_dark():
    """A fitted-like model whose plane has two contents with different decoded brightness: the exemplar's classes
    are numbered darkest first, and a grey target's dark half shows the dark content (its decoded luminance is
    lower there than on the bright half, and each half's source labels are the target's)."""
    from dynbtf.guided import exemplar_classes, guided_btf, target_labels
    from dynbtf.representations.triple_plane import TriplePlane

    model = TriplePlane(32, 32, seed=0)
    plane, labels = two_content_plane()
    with torch.no_grad():
        model.positional_plane().copy_(torch.cat([plane, plane, plane, plane], -1) * 3.0)
    classes = exemplar_classes(model, 2)
    agreement = np.mean(classes == labels.numpy())
    assert agreement >= 0.95 or agreement <= 0.05  # the two contents, in some order
    grey = np.array([[0.1, 0.9]])  # left half dark, right half bright
    assert target_labels(grey, 2).tolist() == [[0, 1]]
    btf = guided_btf(model, grey, classes=2, target_size=2.0, scale=1.0)
    rng = np.random.default_rng(4)
    uv = rng.uniform(0, 1, (4000, 2)) + np.array([[0.0, 5.0]])
    left, right = uv.copy(), uv.copy() + np.array([[1.0, 0.0]])
    w = np.tile([0.0, 0.0, 1.0], (4000, 1))
    lum = np.array([0.2126, 0.7152, 0.0722])
    dark, bright = btf.eval(left, w, w) @ lum, btf.eval(right, w, w) @ lum
    assert dark.mean() < bright.mean()
    from dynbtf.synthesis.guided_blending import source_labels

    assert float((source_labels(btf.synthesizer, torch.from_numpy(left)) == 0).float().mean()) >= 0.95
    assert float((source_labels(btf.synthesizer, torch.from_numpy(right)) == 1).float().mean()) >= 0.95


def test_synth_target_writes_a_guided_image_and_refuses_what_it_cannot_do(tmp_path, monkeypatch, capsys):
    from dynbtf.cli.main import main
    from dynbtf.io import load_image, save_image
    from dynbtf.representations.model_file import save_model
    from dynbtf.representations.triple_plane import TriplePlane

    monkeypatch.setenv("DYNBTF_COMPILED_CACHE", "off")
    save_model(tmp_path / "a.dbtfm", TriplePlane(16, 16, seed=1))
    painted = np.zeros((8, 8, 3))
    painted[:, 4:] = 1.0
    save_image(tmp_path / "target.png", painted)
    assert main(["synth", str(tmp_path / "a.dbtfm"), "--target", str(tmp_path / "target.png"), "--classes", "2",
                 "--scale", "4", "--resolution", "32", "-o", str(tmp_path / "g.exr")]) == 0
    image = load_image(tmp_path / "g.exr")
    assert image.shape == (32, 32, 3) and np.isfinite(image).all()
    assert main(["synth", str(tmp_path / "a.dbtfm"), "--target", str(tmp_path / "target.png"), "--method", "hex",
                 "--scale", "4", "--resolution", "32", "-o", str(tmp_path / "h.exr")]) == 0
    assert not np.array_equal(load_image(tmp_path / "h.exr"), image)  # hex's blend, not hist's
    capsys.readouterr()
    assert main(["synth", str(tmp_path / "a.dbtfm"), "--target", str(tmp_path / "target.png"), "--method", "struct",
                 "--cells", "2", "--scale", "4", "--resolution", "32", "-o", str(tmp_path / "s.exr")]) == 0
    assert np.isfinite(load_image(tmp_path / "s.exr")).all()
    capsys.readouterr()
    for extra, message in ((["--method", "quilt"], "--target: guided synthesis steers hist, hex or struct"),
                           (["--method", "struct"], "--target: guided struct chooses whole cells by class, so give "
                                                    "its cells"),
                           (["--cells", "4"], "--cells: sets struct's cells; give it with --method struct"),
                           (["--classes", "1"], "--classes: expected 2 to 255"),
                           (["--softness", "2"], "--softness: expected a weight factor in [0, 1]")):
        assert main(["synth", str(tmp_path / "a.dbtfm"), "--target", str(tmp_path / "target.png"), *extra,
                     "-o", str(tmp_path / "x.png")]) == 2
        assert message in capsys.readouterr().err
        assert not (tmp_path / "x.png").exists()


def test_guided_hex_tiling_draws_from_the_target_label_on_both_paths():
    plane, labels = two_content_plane()
    target = LabelField(np.array([[0, 1]]), size=4.0)
    synth = GuidedHexTiling(plane, 3, labels=labels, target=target, tileable=False)
    uv = torch.from_numpy(np.random.default_rng(9).uniform(-30, 30, (8000, 2)))
    expected = target.labels(uv)
    assert float((source_labels(synth, uv) == expected).float().mean()) >= 0.95
    fast, reference = synth.latent(uv), synth.reference_latent(uv)
    assert float((fast - reference).abs().max()) < 1e-3  # no inverse table in hex: float32 rounding only
    assert float(((fast[:, 0] > 0).long() == expected).float().mean()) >= 0.95


def element_plane(seed=1):
    """64 x 64 texels of 8 x 8 elements, each dark (label 0, probability 0.35) or bright (label 1), at random."""
    g = torch.Generator().manual_seed(0)
    element = torch.rand(8, 8, 3, generator=g)
    rng = np.random.default_rng(seed)
    plane, labels = torch.zeros(64, 64, 3), np.zeros((64, 64), np.int64)
    for by in range(8):
        for bx in range(8):
            dark = rng.random() < 0.35
            block = (slice(by * 8, by * 8 + 8), slice(bx * 8, bx * 8 + 8))
            plane[block] = element * (0.5 if dark else 1.0) + 0.02 * torch.rand(8, 8, 3, generator=g)
            labels[block] = 0 if dark else 1
    return plane, labels


def test_guided_struct_chooses_whole_cells_by_label_on_both_paths():
    plane, labels = element_plane()
    target = LabelField(np.array([[0, 1]]), size=4.0)
    synth = GuidedCellQuilting(plane, 1, labels=labels, target=target, cells=8)  # a cell per element
    uv = torch.from_numpy(np.random.default_rng(0).uniform(-20, 20, (20000, 2)))
    positions, _ = synth.read_positions(uv)
    shown = torch.from_numpy(labels)[positions[:, 1].floor().long().clamp(0, 63), positions[:, 0].floor().long()
                                     .clamp(0, 63)]
    on_target = float((shown == target.labels(uv)).float().mean())
    assert torch.equal(source_labels(synth, uv), shown)  # what the benchmark counts: the label of the texel read
    plain = CellQuilting(plane, 1, cells=8)
    plain_positions, _ = plain.read_positions(uv)
    plain_shown = torch.from_numpy(labels)[plain_positions[:, 1].floor().long().clamp(0, 63),
                                           plain_positions[:, 0].floor().long().clamp(0, 63)]
    assert on_target >= 0.85 and on_target > float((plain_shown == target.labels(uv)).float().mean()) + 0.2
    assert float((synth.latent(uv) - synth.reference_latent(uv)).abs().max()) < 1e-4  # the fused kernel agrees
    # every cell whose content could match does: its majority label under the chosen offset is its target's
    cells = torch.arange(-50, 50, dtype=torch.int64)
    for row in (torch.zeros_like(cells), cells.flip(0)):
        k = synth.cell_choices(cells, row)
        majority = synth.cell_labels[torch.remainder(cells, 8), torch.remainder(row, 8), k]
        possible = (synth.cell_labels[torch.remainder(cells, 8), torch.remainder(row, 8)]
                    == synth.cell_target(cells, row)[:, None]).any(1)
        assert torch.equal(majority[possible], synth.cell_target(cells, row)[possible])


@pytest.mark.parametrize("kind", [GuidedBlending, GuidedHexTiling])
def test_guided_footprint_queries_read_the_pyramid_at_the_guided_samples(kind):
    """Footprints of guided hist and hex: the numba kernel equals the torch reference (the pyramid read at the
    guided samples' positions with their steered weights), a footprint of at most one texel is the point query,
    and wide footprints move to the exemplar's mean."""
    plane, labels = two_content_plane()
    target = LabelField(np.array([[0, 1]]), size=4.0)
    extra = {"luminance": torch.rand(32, 32, generator=torch.Generator().manual_seed(2))} if kind is GuidedHexTiling \
        else {}
    fast = kind(plane, 3, labels=labels, target=target, softness=0.3, tileable=False, **extra)
    reference = kind(plane, 3, labels=labels, target=target, softness=0.3, tileable=False, fast=False,
                     prepared=fast.prepared, **extra)
    uv = torch.from_numpy(np.random.default_rng(5).uniform(-20, 20, (3000, 2)))
    for texels in (0.5, 3.0, 11.0):
        footprint = torch.full((len(uv),), texels, dtype=torch.float64)
        got, want = fast.filtered_latent(uv, footprint), reference.filtered_latent(uv, footprint)
        tolerance = 2e-2 if kind is GuidedBlending else 1e-4  # hist: the kernel's inverse tables vs the exact
        assert float((got - want).abs().max()) < tolerance * float(want.abs().max()), texels
    point = fast.latent(uv)
    tiny = fast.filtered_latent(uv, torch.full((len(uv),), 0.5, dtype=torch.float64))
    assert float((tiny - point).abs().max()) < 1e-4 * float(point.abs().max())
    wide = fast.filtered_latent(uv, torch.full((len(uv),), 64.0, dtype=torch.float64))
    assert float(wide.std(0).max()) < 0.2 * float(point.std(0).max())
