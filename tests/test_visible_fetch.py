"""Training's fetch at the visible points (Newton step and bilinear fetch): the compiled loops against the torch
operations and float64 (each as accurate as torch's own float32 form), and against a closed form."""

import numpy as np
import pytest
import torch

from dynbtf.representations.visible_fetch import fetch_visible
from dynbtf.texture import fetch_wrap


def inputs(rows, cols, n, seed, channels=5, dtype=torch.float32):
    generator = torch.Generator().manual_seed(seed)
    f_u = torch.randn(rows, cols, channels, generator=generator, dtype=dtype)
    height = 2.0 * torch.rand(rows, cols, generator=generator, dtype=dtype) - 1.0  # channel units (x 0.02: uv)
    points = torch.rand(n, 2, generator=generator, dtype=dtype) * 3 - 1  # wrapped and not
    points[:4] = torch.tensor([[0.0, 0.0], [1.0 - 1e-7, 0.5], [0.5, -1e-8], [-2.0, 3.0]], dtype=dtype)  # seams
    z = 0.02 * torch.randn(n, generator=generator, dtype=dtype)
    slope = torch.randn(n, 2, generator=generator, dtype=dtype)
    slope[4:8] = 0.0  # vertical views: the point does not move
    slope[8:12] = 40.0  # grazing views: the denominator's floor (0.25) holds
    grad_out = torch.randn(n, channels + 1, generator=generator, dtype=dtype)
    return f_u, height, points, z, slope, grad_out


def value_and_gradients(f_u, height, points, z, slope, grad_out, **options):
    f_u, height = f_u.clone().requires_grad_(True), height.clone().requires_grad_(True)
    out = fetch_visible(f_u, height, points, z, slope, 0.02, **options)
    out.backward(grad_out)
    return out.detach(), f_u.grad, height.grad


@pytest.mark.parametrize("far", [False, True])
@pytest.mark.parametrize("shape, n", [((16, 16), 3000), ((12, 20), 1001), ((1, 7), 13), ((64, 64), 4096)])
def test_compiled_loops_are_as_accurate_as_torchs_float32_form(shape, n, far):
    """Against the definition run in float64 on the same inputs: the compiled loops' error is within twice the
    error of the torch operations in float32 plus eight float32 roundings of the largest value (so no tolerance
    comes from one CPU's results). Seams, vertical and grazing views, a one-row plane and the 64 x 64 training size where many
    points share texels. Far from the origin (half the points moved by thousands of repeats) float32 uv keeps a
    few bits of the fraction: the features are compared there, not the gradients, which jump where rounding moves
    a point across a texel edge."""
    f_u, height, points, z, slope, grad_out = inputs(*shape, n, seed=sum(shape) + n)
    if far:
        points[n // 2:] += torch.tensor([3.0e3, -7.0e3])
    compiled = value_and_gradients(f_u, height, points, z, slope, grad_out)
    torch32 = value_and_gradients(f_u, height, points, z, slope, grad_out, compiled=False)
    exact = value_and_gradients(*(t.double() for t in (f_u, height, points, z, slope, grad_out)), compiled=False)
    names = ["features"] if far else ["features", "grad f_u", "grad height"]
    for name, got, theirs, expected in zip(names, compiled, torch32, exact):
        assert got.shape == expected.shape and got.dtype == torch.float32, name
        error = float((got.double() - expected).abs().max())
        torch_error = float((theirs.double() - expected).abs().max())
        roundings = 8 * float(np.finfo(np.float32).eps) * float(expected.abs().max())
        assert error <= 2 * torch_error + roundings, (name, error, torch_error)
    assert float(compiled[2].abs().sum()) > 0  # the height learns (from its channel, and from dz)


@pytest.mark.parametrize("shape", [(16, 16), (12, 20)])
def test_compiled_loops_equal_the_definition_in_float64(shape):
    """Against the torch operations run in float64: the same features and gradients to float32 rounding (which
    the grazing views amplify: their Newton step moves the point by dz times a slope of 40)."""
    f_u, height, points, z, slope, grad_out = inputs(*shape, 3000, seed=1)
    compiled = value_and_gradients(f_u, height, points, z, slope, grad_out)
    reference = value_and_gradients(*(t.double() for t in (f_u, height, points, z, slope, grad_out)), compiled=False)
    for name, got, expected in zip(["features", "grad f_u", "grad height"], compiled, reference):
        torch.testing.assert_close(got.double(), expected, atol=1e-4 * float(expected.abs().max()), rtol=0, msg=name)
    assert float(compiled[2].abs().sum()) > 0  # the height learns (from its channel, and from dz)


@pytest.mark.parametrize("compiled", [True, False])
def test_newton_step_on_a_flat_height_and_a_linear_ramp_closed_form(compiled):
    """Height c everywhere: the denominator is 1 and dz = c - z, so the features are fetched at p + (c - z) s.
    A feature that is a ramp in u (texel j holds j) reads (u W - 0.5) there, and its gradient moves the height
    by d out / d u * s_u * height_scale (the implicit-function rule), spread on p's bilinear corners."""
    rows, cols = 8, 16
    ramp = torch.arange(cols, dtype=torch.float32).repeat(rows, 1)[..., None]  # (8, 16, 1)
    height = torch.full((rows, cols), 1.5, requires_grad=True)  # 0.03 uv
    points = torch.tensor([[0.30, 0.40], [0.42, 0.77]])
    z = torch.tensor([0.01, 0.02])
    slope = torch.tensor([[0.5, 0.0], [-1.0, 0.25]])
    out = fetch_visible(ramp, height, points, z, slope, 0.02, compiled=compiled)
    q = points + (0.03 - z)[:, None] * slope
    torch.testing.assert_close(out[:, 0], q[:, 0] * cols - 0.5, atol=1e-5, rtol=0)
    torch.testing.assert_close(out[:, 1], torch.full((2,), 1.5), atol=1e-6, rtol=0)
    out[:, 0].sum().backward()
    # d out / d q_u = cols; d q_u / d height_channel(p) = s_u * height_scale (the denominator is 1)
    expected_total = float((cols * slope[:, 0] * 0.02).sum())
    torch.testing.assert_close(float(height.grad.sum()), expected_total, atol=1e-5, rtol=0)


def test_without_newton_movement_it_is_fetch_wrap():
    """z equal to the height at p: dz = 0 and the features are fetch_wrap of concat(f_U, height) at p."""
    f_u, _, points, _, slope, _ = inputs(10, 14, 500, seed=2)
    height = torch.full((10, 14), 0.75)
    z = torch.full((500,), 0.75 * 0.02)
    expected = fetch_wrap(torch.cat([f_u, height[..., None]], -1).double(), points.double())
    got = fetch_visible(f_u, height, points, z, slope, 0.02)
    torch.testing.assert_close(got.double(), expected, atol=1e-5, rtol=0)
    assert np.isfinite(got.numpy()).all()
