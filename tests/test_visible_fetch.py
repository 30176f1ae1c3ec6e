"""The fetch at the visible points (training's Newton step and bilinear fetch): compiled kernel vs torch ops."""

import numpy as np
import pytest
import torch

from dynbtf.representations import parallax_kernels
from dynbtf.representations.parallax import ParallaxTriplePlane, march_visible_uv
from dynbtf.representations.visible_fetch import fetch_visible
from dynbtf.texture import fetch_wrap


def inputs(rows, cols, n, seed, dtype=torch.float32):
    generator = torch.Generator().manual_seed(seed)
    f_u = torch.randn(rows, cols, 5, generator=generator, dtype=dtype)
    height = 2.0 * torch.rand(rows, cols, generator=generator, dtype=dtype)  # channel units (x 0.02: uv)
    points = torch.rand(n, 2, generator=generator, dtype=dtype) * 3 - 1  # wrapped and not
    points[:4] = torch.tensor([[0.0, 0.0], [1.0 - 1e-7, 0.5], [0.5, -1e-8], [-2.0, 3.0]], dtype=dtype)  # seams
    z = 0.04 * torch.rand(n, generator=generator, dtype=dtype)
    slope = torch.randn(n, 2, generator=generator, dtype=dtype)
    slope[4:8] = 0.0  # vertical views: the point does not move
    grad_out = torch.randn(n, 6, generator=generator, dtype=dtype)
    return f_u, height, points, z, slope, grad_out


def value_and_gradients(f_u, height, points, z, slope, grad_out, **options):
    f_u, height = f_u.clone().requires_grad_(True), height.clone().requires_grad_(True)
    out = fetch_visible(f_u, height, points, z, slope, 0.02, **options)
    out.backward(grad_out)
    return out.detach(), f_u.grad, height.grad


@pytest.mark.parametrize("newton", [True, False])
@pytest.mark.parametrize("shape", [(16, 16), (12, 20)])
def test_kernel_equals_the_torch_definition_in_float64(shape, newton):
    """The compiled kernel (float32 planes, float64 inside) against the torch ops run in float64
    (grid_sample, autograd): same features and same gradients for f_U and the height."""
    f_u, height, points, z, slope, grad_out = inputs(*shape, 3000, seed=1)
    kernel = value_and_gradients(f_u, height, points, z, slope, grad_out, newton=newton)
    reference = value_and_gradients(*(t.double() for t in (f_u, height, points, z, slope, grad_out)),
                                    newton=newton, kernel=False)
    assert kernel[0].dtype == torch.float32 and kernel[0].shape == (3000, 6)
    for name, got, expected in zip(["features", "grad f_u", "grad height"], kernel, reference):
        scale = float(expected.abs().max())
        torch.testing.assert_close(got.double(), expected, atol=2e-6 * scale, rtol=0, msg=name)
    assert float(kernel[2].abs().sum()) > 0  # the height learns (from its channel, and from dz with newton)


def test_newton_step_on_a_flat_height_and_a_linear_ramp_closed_form():
    """Height c everywhere: the denominator is 1 and dz = c - z, so the features are fetched at p + (c - z) s.
    A feature that is a ramp in u (texel j holds j) reads (u W - 0.5) there, and its gradient moves the height
    by d out / d u * s_u * height_scale (the implicit-function rule), spread on p's bilinear corners."""
    rows, cols = 8, 16
    ramp = torch.arange(cols, dtype=torch.float32).repeat(rows, 1)[..., None]  # (8, 16, 1)
    height = torch.full((rows, cols), 1.5, requires_grad=True)  # 0.03 uv
    points = torch.tensor([[0.30, 0.40], [0.42, 0.77]])
    z = torch.tensor([0.01, 0.02])
    slope = torch.tensor([[0.5, 0.0], [-1.0, 0.25]])
    out = fetch_visible(ramp, height, points, z, slope, 0.02, newton=True)
    q = points + (0.03 - z)[:, None] * slope
    torch.testing.assert_close(out[:, 0], q[:, 0] * cols - 0.5, atol=1e-5, rtol=0)
    torch.testing.assert_close(out[:, 1], torch.full((2,), 1.5), atol=1e-6, rtol=0)
    out[:, 0].sum().backward()
    # d out / d q_u = cols; d q_u / d height_channel(p) = s_u * height_scale (the denominator is 1)
    expected_total = float((cols * slope[:, 0] * 0.02).sum())
    torch.testing.assert_close(float(height.grad.sum()), expected_total, atol=1e-5, rtol=0)


def test_kernel_fetches_as_fetch_wrap_without_newton_far_from_the_origin():
    f_u, height, points, z, slope, _ = inputs(10, 14, 500, seed=2)
    far = points + torch.tensor([3.0e3, -7.0e3])
    expected = fetch_wrap(torch.cat([f_u, height[..., None]], -1).double(), far.double())
    got = fetch_visible(f_u, height, far, z, slope, 0.02, newton=False)
    torch.testing.assert_close(got.double(), expected, atol=1e-4, rtol=0)  # far's float32 rounding of uv


def parallax_model():
    model = ParallaxTriplePlane(16, 12, seed=5)
    relief = torch.nn.functional.avg_pool2d(torch.rand(1, 1, 16, 12, generator=torch.Generator().manual_seed(1)), 3,
                                            1, 1, count_include_pad=False)[0, 0]
    model.set_height(0.06 * relief)
    return model


def views_and_lights(groups, per_group, seed):
    generator = torch.Generator().manual_seed(seed)
    shift = torch.tensor([0.5, 0.5, -0.2])  # z in [0.2, 1.2] before normalizing: above the horizon
    views = torch.nn.functional.normalize(torch.rand(groups, 3, generator=generator) - shift, dim=-1)
    lights = torch.nn.functional.normalize(torch.rand(groups * per_group, 3, generator=generator) - shift, dim=-1)
    return views.repeat_interleave(per_group, 0), lights


def test_training_loss_is_the_same_with_the_compiled_kernels_and_with_torch_ops():
    """The model's fused training loss and its gradients (after a first step, so that the Newton step moves the
    points) do not depend on which form of the table, march and fetch runs."""

    def run(compiled):
        model = parallax_model()
        model.use_compiled_kernels = compiled
        w_view, w_light = views_and_lights(4, 2, seed=3)
        target = torch.rand(2, 192, 3, generator=torch.Generator().manual_seed(4))
        model.texel_image_l1_loss(w_view, w_light, target, texel_groups=4).backward()
        with torch.no_grad():  # the height moves a little, below the refresh threshold: no new march
            model.height_channel -= 0.2 * model.height_channel.grad.sign() * 1e-2
        model.zero_grad()
        loss = model.texel_image_l1_loss(w_view, w_light, target, texel_groups=4)
        loss.backward()
        return loss.detach(), {name: p.grad for name, p in model.named_parameters()}

    (loss_kernel, grads_kernel), (loss_torch, grads_torch) = run(True), run(False)
    torch.testing.assert_close(loss_kernel, loss_torch, atol=1e-5, rtol=0)
    for name in grads_torch:
        scale = float(grads_torch[name].abs().max())
        torch.testing.assert_close(grads_kernel[name], grads_torch[name], atol=1e-3 * scale, rtol=0, msg=name)


def test_compiled_table_marches_the_same_rays_as_visible_uv():
    """The compiled table (read, missing rows marched) holds the points of the torch path bit for bit, and the
    heights there to rounding, whichever rows a step asks for first; views below the horizon march vertically."""
    compiled, reference = parallax_model(), parallax_model()
    reference.use_compiled_kernels = False
    w_view, _ = views_and_lights(6, 1, seed=7)
    w_view[5] = torch.tensor([0.6, 0.0, -0.8])  # below the horizon: treated as vertical
    generator = torch.Generator().manual_seed(8)
    for _ in range(3):  # steps asking for overlapping texel sets
        texels = torch.randint(0, 16 * 12, (6, 40), generator=generator)
        got, expected = compiled._visible_texel_points(w_view, texels), reference._visible_texel_points(w_view, texels)
        assert torch.equal(got[0], expected[0])
        torch.testing.assert_close(got[1], expected[1], atol=1e-9, rtol=0)
    assert torch.equal(compiled._visible_cache.marched, reference._visible_cache.marched)
    vertical = compiled._visible_texel_points(w_view[5:], torch.arange(5)[None])[0][0]
    torch.testing.assert_close(vertical, compiled._texel_centres[:5].float(), atol=0, rtol=0)


def test_small_marches_on_the_calling_thread_give_the_same_rays(monkeypatch):
    """march_plane runs few rays serially and many in parallel: the rays are the same, bit for bit."""
    generator = torch.Generator().manual_seed(4)
    plane = 0.04 * torch.rand(20, 20, dtype=torch.float64, generator=generator)
    uv = torch.rand(2000, 2, dtype=torch.float64, generator=generator) * 3
    w = torch.nn.functional.normalize(torch.rand(2000, 3, dtype=torch.float64, generator=generator)
                                      + torch.tensor([0, 0, 0.2], dtype=torch.float64), dim=-1)
    options = dict(h_min=float(plane.min()), h_max=float(plane.max()), step=0.025, max_step=0.4)
    parallel = march_visible_uv(uv, w, plane, **options)
    monkeypatch.setattr(parallax_kernels, "PARALLEL_MARCH_RAYS", 10 ** 9)
    serial = march_visible_uv(uv, w, plane, **options)
    assert np.array_equal(parallel.numpy(), serial.numpy())
