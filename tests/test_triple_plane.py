"""Triple Plane: shapes, paper defaults, gradients, and the fast whole-image path vs the plain forward."""

import pytest
import torch
import torch.nn.functional as F

from dynbtf.conventions import angular_plane_coords, half_diff_from_view_light, texel_centers_uv
from dynbtf.errors import InputError
from dynbtf.representations import get_representation_class
from dynbtf.representations.triple_plane import TriplePlane
from dynbtf.texture import fetch_angular, fetch_wrap
from dynbtf.decoder.fused_mlp import split_mlp_l1_loss


def random_directions(shape, generator, dtype=torch.float32):
    w = torch.randn(*shape, 3, generator=generator, dtype=torch.float64)
    w[..., 2] = w[..., 2].abs() + 0.05
    return F.normalize(w, dim=-1).to(dtype)


def test_defaults_are_the_papers():
    model = TriplePlane(40, 30)
    assert model.f_u.shape == (40, 30, 16)
    assert model.f_h.shape == model.f_d.shape == (20, 20, 8)
    linears = [model.decoder.first, *model.decoder.rest]
    assert [(l.in_features, l.out_features) for l in linears] == [(32, 32), (32, 32), (32, 32), (32, 3)]
    assert get_representation_class("triple") is TriplePlane
    rebuilt = TriplePlane(**model.config())
    assert all(torch.equal(a, b) for a, b in zip(model.state_dict().values(), rebuilt.state_dict().values()))
    # He initialization: N(0, 2 / C) per plane
    assert abs(float(model.f_u.detach().std()) - (2 / 16) ** 0.5) < 0.01
    assert abs(float(model.f_h.detach().std()) - (2 / 8) ** 0.5) < 0.05


def test_sizes_are_parameters_and_bad_sizes_fail():
    model = TriplePlane(5, 6, positional_channels=4, angular_resolution=7, angular_channels=3, hidden=9, layers=3)
    assert model.f_u.shape == (5, 6, 4) and model.f_h.shape == (7, 7, 3)
    assert model.decoder.first.in_features == 10 and len(model.decoder.rest) == 2
    with pytest.raises(InputError, match="height"):
        TriplePlane(0, 4)
    with pytest.raises(InputError, match="layers"):
        TriplePlane(4, 4, layers=1)


@pytest.mark.parametrize("batch", [(), (7,), (2, 3), (2, 1, 4)])
def test_output_shapes_for_any_batch_shape(batch):
    g = torch.Generator().manual_seed(1)
    model = TriplePlane(6, 5, seed=1)
    uv = torch.rand(*batch, 2, generator=g) * 3 - 1
    wv, wl = random_directions(batch, g), random_directions(batch, g)
    assert model(uv, wv, wl).shape == (*batch, 3)
    assert model.angular_features(wv, wl).shape == (*batch, 16)
    assert model.decode(model.positional_features(uv), wv, wl).shape == (*batch, 3)


def test_forward_matches_an_independent_composition():
    g = torch.Generator().manual_seed(2)
    model = TriplePlane(6, 5, seed=2)
    uv = torch.rand(11, 2, generator=g, dtype=torch.float64)
    wv, wl = random_directions((11,), g), random_directions((11,), g)
    h, d = half_diff_from_view_light(wv, wl)
    x = torch.cat([fetch_wrap(model.f_u, uv), fetch_angular(model.f_h, angular_plane_coords(h)),
                   fetch_angular(model.f_d, angular_plane_coords(d))], dim=-1)
    layers = [model.decoder.first, *model.decoder.rest]
    for k, layer in enumerate(layers):
        x = layer(x)
        if k < len(layers) - 1:
            x = F.leaky_relu(x, 0.01)
    torch.testing.assert_close(model(uv, wv, wl), x, rtol=1e-5, atol=1e-6)


def test_decode_with_angular_broadcasts_like_decode():
    g = torch.Generator().manual_seed(3)
    model = TriplePlane(4, 4)
    feats = torch.randn(9, 16, generator=g)
    wv, wl = random_directions((5,), g), random_directions((5,), g)
    angular = model.angular_features(wv, wl)  # (5, 16)
    broadcast = model.decode_with_angular(feats[None], angular[:, None])  # (5, 9, 3)
    explicit = model.decode(feats[None].expand(5, 9, 16), wv[:, None].expand(5, 9, 3), wl[:, None].expand(5, 9, 3))
    torch.testing.assert_close(broadcast, explicit, rtol=1e-5, atol=1e-6)


def test_gradcheck_float64():
    g = torch.Generator().manual_seed(4)
    model = TriplePlane(3, 4, positional_channels=2, angular_resolution=4, angular_channels=2, hidden=4).double()
    uv = torch.rand(5, 2, generator=g, dtype=torch.float64)
    wv, wl = random_directions((5,), g, torch.float64), random_directions((5,), g, torch.float64)
    names = ["f_u", "f_h", "f_d", "decoder.first.weight", "decoder.rest.2.bias"]
    params = dict(model.named_parameters())

    def f(*tensors):
        return torch.func.functional_call(model, {**params, **dict(zip(names, tensors))}, (uv, wv, wl))

    inputs = tuple(params[n].detach().clone().requires_grad_() for n in names)
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6)


def test_gradcheck_fused_loss_float64():
    g = torch.Generator().manual_seed(5)
    layers = [torch.nn.Linear(4, 4).double(), torch.nn.Linear(4, 3).double()]
    pos = torch.randn(7, 4, generator=g, dtype=torch.float64, requires_grad=True)
    img = torch.randn(2, 4, generator=g, dtype=torch.float64, requires_grad=True)
    target = torch.randn(2, 7, 3, generator=g, dtype=torch.float64)

    def f(p, q, w):
        layers[0].weight.data = w
        return split_mlp_l1_loss(p, q, layers, 0.01, target, chunk_texels=3)

    w0 = layers[0].weight.detach().clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda p, q: split_mlp_l1_loss(p, q, layers, 0.01, target, chunk_texels=3),
                                    (pos, img), eps=1e-6, atol=1e-6)
    # weights' gradients via the Function's own outputs vs autograd of the plain expression
    loss = f(pos, img, w0.detach())
    grads = torch.autograd.grad(loss, [layers[0].weight, layers[1].weight, layers[1].bias])
    x = F.leaky_relu(pos[None] + img[:, None], 0.01)
    ref = (layers[1](F.leaky_relu(layers[0](x), 0.01)) - target).abs().mean()
    ref_grads = torch.autograd.grad(ref, [layers[0].weight, layers[1].weight, layers[1].bias])
    torch.testing.assert_close(loss, ref)
    for a, b in zip(grads, ref_grads):
        torch.testing.assert_close(a, b)


@pytest.mark.parametrize("workers,chunk", [(1, 256), (2, 5)])
@pytest.mark.parametrize("subset", [False, True])
def test_fast_training_path_equals_naive_forward(workers, chunk, subset):
    """Same loss and gradients as the plain forward (three grid_sample fetches per sample) at texel centres."""
    g = torch.Generator().manual_seed(6)
    h, w, b = 9, 7, 3
    model = TriplePlane(h, w, seed=6)
    wv, wl = random_directions((b,), g), random_directions((b,), g)
    texels = torch.tensor([0, 5, 17, 40, 62]) if subset else None
    n = 5 if subset else h * w
    target = torch.rand(b, n, 3, generator=g)
    uv = torch.from_numpy(texel_centers_uv(h, w)).reshape(-1, 2)
    if subset:
        uv = uv[texels]
    naive = (model(uv[None].expand(b, n, 2), wv[:, None].expand(b, n, 3), wl[:, None].expand(b, n, 3)) - target)
    naive = naive.abs().mean()
    naive_grads = torch.autograd.grad(naive, list(model.parameters()))
    images = model.predict_texel_images(wv, wl, texels)
    torch.testing.assert_close(images, model(uv[None].expand(b, n, 2), wv[:, None].expand(b, n, 3),
                                             wl[:, None].expand(b, n, 3)), rtol=1e-5, atol=1e-6)
    fast = model.texel_image_l1_loss(wv, wl, target, texels, chunk_texels=chunk, workers=workers)
    fast_grads = torch.autograd.grad(fast, list(model.parameters()))
    torch.testing.assert_close(fast, naive, rtol=1e-5, atol=1e-7)
    for (name, _), a, c in zip(model.named_parameters(), fast_grads, naive_grads):
        torch.testing.assert_close(a, c, rtol=1e-4, atol=1e-7, msg=name)


@pytest.mark.parametrize("workers,chunk", [(1, 256), (2, 3), (2, 9)])  # several groups per chunk; pieces
def test_grouped_fused_loss_equals_per_group_naive_forward(workers, chunk):
    """Texel groups, each under its own images: same loss and gradients as the plain forward per group."""
    g = torch.Generator().manual_seed(8)
    h, w, b = 6, 5, 2
    model = TriplePlane(h, w, seed=8)
    groups = [torch.tensor([3, 4, 11, 29]), torch.tensor([0, 7, 8, 9]), torch.tensor([1, 2, 12, 20])]
    texels = torch.cat(groups)
    wv, wl = random_directions((3 * b,), g), random_directions((3 * b,), g)
    target = torch.rand(b, len(texels), 3, generator=g)
    uv_all = torch.from_numpy(texel_centers_uv(h, w)).reshape(-1, 2)
    total = 0.0
    for k, tex in enumerate(groups):
        uv = uv_all[tex]
        n = len(tex)
        pred = model(uv[None].expand(b, n, 2), wv[k * b:(k + 1) * b, None].expand(b, n, 3),
                     wl[k * b:(k + 1) * b, None].expand(b, n, 3))
        total = total + (pred - target[:, 4 * k:4 * k + 4]).abs().sum()
    naive = total / target.numel()
    naive_grads = torch.autograd.grad(naive, list(model.parameters()))
    fast = model.texel_image_l1_loss(wv, wl, target, texels, chunk_texels=chunk, workers=workers, texel_groups=3)
    fast_grads = torch.autograd.grad(fast, list(model.parameters()))
    torch.testing.assert_close(fast, naive, rtol=1e-5, atol=1e-7)
    for (name, _), a, c in zip(model.named_parameters(), fast_grads, naive_grads):
        torch.testing.assert_close(a, c, rtol=1e-4, atol=1e-7, msg=name)


def test_fused_loss_rejects_bad_shapes():
    layers = [torch.nn.Linear(4, 3)]
    with pytest.raises(InputError, match="target"):
        split_mlp_l1_loss(torch.zeros(5, 4), torch.zeros(2, 4), layers, 0.01, torch.zeros(2, 4, 3))
    with pytest.raises(InputError, match="image_pre"):
        split_mlp_l1_loss(torch.zeros(5, 4), torch.zeros(2, 3), layers, 0.01, torch.zeros(2, 5, 3))
    with pytest.raises(InputError, match="texel groups"):
        split_mlp_l1_loss(torch.zeros(5, 4), torch.zeros(2, 2, 4), layers, 0.01, torch.zeros(2, 5, 3))


def test_query_shape_errors_name_the_argument():
    model = TriplePlane(4, 4)
    w = torch.tensor([[0.0, 0.0, 1.0]])
    with pytest.raises(InputError, match="w_light"):
        model(torch.zeros(1, 2), w, torch.zeros(2, 3))
