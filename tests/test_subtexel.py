"""The sub-texel term of training (``TrainConfig.subtexel``): its points read what the bilinear fetch reads, its loss
is the plain L1 of decoded bilinear fetches (value and gradients), and a fit uses it where it applies."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dynbtf.errors import InputError
from dynbtf.representations.triple_plane import TriplePlane
from dynbtf.texture import fetch_wrap
from dynbtf.training.batches import between_texel_points
from dynbtf.training.fit import TrainConfig, check_options


def _mix(plane: torch.Tensor, neighbours: np.ndarray, weights: np.ndarray) -> torch.Tensor:
    flat = plane.reshape(-1, plane.shape[-1])
    return sum(torch.from_numpy(weights[k])[:, None] * flat[torch.from_numpy(neighbours[k])] for k in range(4))


@pytest.mark.parametrize("size", [(6, 8), (1, 5), (7, 1)])
def test_points_mix_the_texels_the_bilinear_fetch_reads(size):
    h, w = size
    plane = torch.rand(h, w, 5, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    neighbours, weights, uv = between_texel_points(h, w, 500, np.random.default_rng(1))
    assert ((0 <= uv) & (uv < 1 + 1 / min(h, w))).all() and (weights >= 0).all()
    reference = fetch_wrap(plane, torch.from_numpy(uv))
    torch.testing.assert_close(_mix(plane, neighbours, weights.astype(np.float64)), reference, atol=1e-6, rtol=0)


@pytest.mark.parametrize("with_taps", [False, True])
def test_subtexel_loss_is_the_l1_of_decoded_bilinear_fetches(with_taps):
    """The torch path, and with the pairs' angular taps (what the fit passes) the native kernels' weighted texel
    fetch where they run: the same value and gradients as decoding the renderer's bilinear fetch."""
    from dynbtf.decoder import fused_mlp

    model = TriplePlane(6, 8, seed=1)
    neighbours, weights, uv = between_texel_points(6, 8, 40, np.random.default_rng(2))
    rng = np.random.default_rng(3)
    directions = rng.normal(size=(2, 3, 3))
    directions[..., 2] = np.abs(directions[..., 2]) + 0.2
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    w_view, w_light = (torch.from_numpy(d).float() for d in directions)
    target = torch.rand(3, 40, 3, generator=torch.Generator().manual_seed(4))

    taps = model.direction_taps(w_view, w_light) if with_taps else None
    calls = []
    real = fused_mlp._TriplePlaneL1.apply
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(fused_mlp._TriplePlaneL1, "apply", lambda *a: calls.append(1) or real(*a))
        loss = model.subtexel_l1_loss(torch.from_numpy(neighbours), torch.from_numpy(weights), w_view, w_light,
                                      target, chunk_texels=8, workers=2, angular_taps=taps)
    native = with_taps and fused_mlp._native_library() is not None
    assert calls == ([1] if native else [])
    loss.backward()
    ours = {name: p.grad.clone() for name, p in model.named_parameters()}
    model.zero_grad()

    features = fetch_wrap(model.f_u, torch.from_numpy(uv).float())  # (40, C), the fetch a renderer makes
    n = features.shape[0]
    decoded = torch.stack([model.decode(features, w_view[b].expand(n, 3), w_light[b].expand(n, 3))
                           for b in range(3)])
    reference = (decoded - target).abs().mean()
    reference.backward()
    torch.testing.assert_close(loss, reference, atol=1e-5, rtol=1e-5)
    for name, p in model.named_parameters():
        torch.testing.assert_close(ours[name], p.grad, atol=1e-5, rtol=1e-4, msg=name)


def test_the_option_is_checked_and_refused_where_it_does_not_apply(tmp_path):
    with pytest.raises(InputError, match=r"--subtexel \(TrainConfig.subtexel\): expected a finite number in "
                                         r"\[0, 1000\] \(or unset\), got -1.0"):
        check_options(subtexel=-1.0)
    from dynbtf.data.open import open_btf
    from dynbtf.training import get_fitter

    with pytest.raises(InputError, match="--subtexel .*'triple-parallax' representation has no sub-texel term"):
        get_fitter("triple-parallax")(open_btf("sim:leather?size=16"), tmp_path / "m.dbtfm",
                                      TrainConfig(epochs=1, subtexel=1.0))
    with pytest.raises(InputError, match="--repr auto races it against triple-parallax"):
        from dynbtf.training.model_choice import fit_best

        fit_best(open_btf("sim:leather?size=16"), tmp_path / "a.dbtfm", TrainConfig(epochs=1, subtexel=1.0))
    with pytest.raises(InputError, match="--subtexel .*closed form"):
        get_fitter("pca")(open_btf("sim:leather?size=16"), tmp_path / "p.dbtfm", TrainConfig(subtexel=0.5))


def test_a_fit_with_the_term_records_it_and_a_run_without_it_is_another_run(tmp_path):
    from dynbtf.data.open import open_btf
    from dynbtf.representations.model_file import read_model_metadata
    from dynbtf.training import get_fitter

    source, output = open_btf("sim:leather?size=16"), tmp_path / "m.dbtfm"
    config = TrainConfig(epochs=1, images_per_step=4, subtexel=0.5, monitor_pairs=2)
    result = get_fitter("triple")(source, output, config, progress=False)
    assert result.finished and read_model_metadata(output)["provenance"]["run"]["subtexel"] == 0.5
    with pytest.raises(InputError, match=r"differs in \['subtexel'\]"):
        get_fitter("triple")(source, output, TrainConfig(epochs=1, images_per_step=4, monitor_pairs=2),
                             progress=False)


def test_unset_is_the_triple_planes_own_weight_and_nothing_for_the_kinds_without_the_term():
    from dynbtf.data.open import open_btf
    from dynbtf.representations.parallax import ParallaxTriplePlane
    from dynbtf.training.fit import AUTO_SUBTEXEL, subtexel_weight
    from dynbtf.training.recipe import auto_recipe

    triple, parallax = TriplePlane(4, 4), ParallaxTriplePlane(4, 4)
    assert subtexel_weight(triple, TrainConfig(subtexel=None)) == AUTO_SUBTEXEL > 0
    assert subtexel_weight(parallax, TrainConfig(subtexel=None)) == 0.0
    assert subtexel_weight(triple, TrainConfig()) == 0.0  # the library's default: the paper's recipe
    assert subtexel_weight(triple, TrainConfig(subtexel=2.0)) == 2.0
    with pytest.raises(InputError, match="'triple-parallax' representation has no sub-texel term"):
        subtexel_weight(parallax, TrainConfig(subtexel=1.0))
    recipe = auto_recipe(open_btf("sim:leather?size=16"))
    assert recipe.config.subtexel is None and f"sub-texel term x{AUTO_SUBTEXEL:g} with the Triple Plane" in recipe.summary
    assert auto_recipe(open_btf("sim:leather?size=16"), subtexel=0.0).config.subtexel == 0.0


def test_the_image_cache_refuses_texels_outside_the_images():
    """ImageStore.get gathers flat (image, texel) rows: an index outside the image would read a neighbouring image,
    so it is refused with the valid range."""
    from dynbtf.data.open import open_btf
    from dynbtf.training.images import ImageStore

    store = ImageStore(open_btf("sim:leather?size=8&grid=ubo2003"))
    pairs = np.array([[0, 0], [1, 2]])
    got = store.get(pairs, np.array([0, 63, 5]))
    assert got.shape == (2, 3, 3) and got.dtype == np.float32
    np.testing.assert_array_equal(got[1, 1], store.image(1, 2)[63])
    for bad in (np.array([64]), np.array([-1, 3])):
        with pytest.raises(InputError, match=r"get: texel indices must be in \[0, 64\), got"):
            store.get(pairs, bad)
