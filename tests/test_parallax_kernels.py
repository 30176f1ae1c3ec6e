"""Training's visible-point table on the CPU (compiled: read, and missing rows marched, in one loop) against the
torch operations every other device runs, and the march's serial and parallel drivers."""

import numpy as np
import torch

from dynbtf.representations import parallax_kernels
from dynbtf.representations.parallax import ParallaxTriplePlane, march_visible_uv


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


def test_training_loss_is_the_same_with_the_compiled_table_and_with_torch_ops():
    """The model's fused training loss and its gradients (after a first step, so that the Newton step moves the
    points) are the same whichever form of the table and the fetch runs: the loss to float32 rounding, each
    gradient to 64 float32 roundings of its largest entry (the two forms sum the points that share a texel in
    another order; ``benchmarks/bench_parallax_training.py --quality`` compares whole fits over seeds)."""

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
    eps = float(torch.finfo(torch.float32).eps)
    torch.testing.assert_close(loss_kernel, loss_torch, atol=4 * eps * float(loss_torch.abs()), rtol=0)
    for name in grads_torch:
        scale = float(grads_torch[name].abs().max())
        assert scale > 0, name  # every parameter learns in this step
        torch.testing.assert_close(grads_kernel[name], grads_torch[name], atol=64 * eps * scale, rtol=0, msg=name)


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
