"""The native fused training kernel (dynbtf/decoder/native/fused_mlp.cpp) against the PyTorch path it replaces.

References: the chunked PyTorch implementation of the same loss (itself tested against autograd and
gradcheck in test_triple_plane.py) and plain autograd in float64. Targets are placed 0.3 away from the
prediction so that no residual sits near zero, where sign(r) -- the L1 gradient -- would flip under
rounding differences between two correct implementations.
"""

import shutil

import pytest
import torch
from torch import nn

from dynbtf.decoder import native
from dynbtf.errors import InputError
from dynbtf.decoder import fused_mlp
from dynbtf.decoder.fused_mlp import native_precisions, resolve_precision, split_mlp_l1_loss

needs_native = pytest.mark.skipif(not native_precisions(), reason="no native kernel on this machine")
needs_bf16 = pytest.mark.skipif("bf16" not in native_precisions(), reason="CPU without AVX512-BF16")


def problem(groups, images, texels, hidden=32, out=3, layers=3, seed=0):
    """Random P, Q, layers and a target 0.3 away from the MLP's output (no residual near 0)."""
    g = torch.Generator().manual_seed(seed)
    p = torch.randn(groups * texels, hidden, generator=g).requires_grad_()
    q = torch.randn(groups, images, hidden, generator=g).requires_grad_()
    torch.manual_seed(seed)
    mlp = [nn.Linear(hidden, hidden) for _ in range(layers - 1)] + [nn.Linear(hidden, out)]
    with torch.no_grad():
        pre = p.view(groups, 1, texels, hidden) + q.view(groups, images, 1, hidden)
        x = nn.functional.leaky_relu(pre, 0.01)
        for layer in mlp[:-1]:
            x = nn.functional.leaky_relu(layer(x), 0.01)
        y = mlp[-1](x).transpose(0, 1).reshape(images, groups * texels, out)
        sign = torch.where(torch.rand(y.shape, generator=g) > 0.5, 1.0, -1.0)
    return p, q, mlp, (y + 0.3 * sign).contiguous()


def loss_and_grads(p, q, mlp, target, use_native, monkeypatch=None, **kw):
    for t in [p, q, *[x for layer in mlp for x in layer.parameters()]]:
        t.grad = None
    if not use_native:
        monkeypatch.setattr(fused_mlp, "_native_supports", lambda *a: False)
    loss = split_mlp_l1_loss(p, q, mlp, 0.01, target, **kw)
    loss.backward()
    if not use_native:
        monkeypatch.undo()
    return [loss.detach(), p.grad, q.grad, *[x.grad for layer in mlp for x in layer.parameters()]]


def test_a_compiler_means_a_native_kernel():
    """Where a C++ compiler exists the kernel must build: a silent fallback would hide a broken build."""
    if not any(shutil.which(c) for c in ("g++", "c++", "clang++")):
        pytest.skip("no C++ compiler")
    assert "fp32" in native_precisions(), native.status("fused_mlp")
    assert native.status("fused_mlp").startswith("loaded ")


@needs_native
def test_the_kernel_reports_its_argument_layout_and_shapes():
    """The C++ struct and its ctypes mirror have one size; the shape rule is the kernel's own answer."""
    import ctypes

    library = fused_mlp._native_library()
    assert library.dynbtf_fused_l1_args_size() == ctypes.sizeof(fused_mlp._NativeArgs)
    supported = {(h, c, n) for h in range(16, 145, 16) for c in (1, 3, 16, 17) for n in (1, 3, 7, 8)
                 if library.dynbtf_fused_l1_supports(h, c, n)}
    # the kernel's template instances: 16, 32, 48, 64 and 128 hidden units, 1..16 outputs, 1..7 layers
    assert supported == {(h, c, n) for h in (16, 32, 48, 64, 128) for c in (1, 3, 16) for n in (1, 3, 7)}
    assert not library.dynbtf_fused_l1_supports(24, 3, 3)


@needs_native
def test_shapes_without_a_native_path_train_through_pytorch(monkeypatch):
    """80 hidden units has no template instance: the loss still comes out, equal to the PyTorch path's."""
    p, q, mlp, target = problem(2, 3, 16, hidden=80)
    assert not fused_mlp._native_supports(p, [layer.weight for layer in mlp], "fp32")
    got = loss_and_grads(p, q, mlp, target, True, chunk_texels=8)
    want = loss_and_grads(p, q, mlp, target, False, monkeypatch, chunk_texels=8)
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b)


@needs_native
@pytest.mark.parametrize("groups,images,texels,hidden,out,layers,chunk,workers", [
    (1, 16, 300, 32, 3, 3, 64, 2),   # the Triple Plane's decoder; tiles with a 44-texel tail
    (4, 16, 37, 32, 3, 3, 16, 2),    # texel groups, chunks and tiles not multiples of 8
    (2, 3, 100, 64, 5, 4, 1000, 1),  # wider, deeper, 5 outputs
    (1, 4, 9, 16, 1, 2, 4, 3),       # narrow, one hidden layer, 1 output, more workers than needed
])
def test_native_fp32_equals_the_torch_path(monkeypatch, groups, images, texels, hidden, out, layers, chunk, workers):
    p, q, mlp, target = problem(groups, images, texels, hidden, out, layers)
    kw = dict(chunk_texels=chunk, workers=workers)
    reference = loss_and_grads(p, q, mlp, target, False, monkeypatch, **kw)
    result = loss_and_grads(p, q, mlp, target, True, **kw)
    for name, a, b in zip(["loss", "P", "Q", *[f"param{k}" for k in range(2 * layers)]], result, reference):
        torch.testing.assert_close(a, b, rtol=2e-5, atol=2e-6 * float(b.abs().max()), msg=name)


def float64_reference(p, q, mlp, target, slope=0.01):
    """The loss and every gradient ``[loss, dP, dQ, dW_2, dc_2, ...]`` of the un-split MLP in float64 autograd on
    the concatenated batch: ``P (G * n, H)``, ``Q (G, B, H)``, ``target (B, G * n, C)``."""
    groups, images, hidden = q.shape
    n = p.shape[0] // groups
    p64, q64 = p.detach().double().requires_grad_(), q.detach().double().requires_grad_()
    mlp64 = [nn.Linear(l.in_features, l.out_features).double() for l in mlp]
    for a, b in zip(mlp64, mlp):
        a.load_state_dict({k: v.double() for k, v in b.state_dict().items()})
    x = nn.functional.leaky_relu(p64.view(groups, 1, n, hidden) + q64.view(groups, images, 1, hidden), slope)
    for layer in mlp64[:-1]:
        x = nn.functional.leaky_relu(layer(x), slope)
    y = mlp64[-1](x).transpose(0, 1).reshape(images, groups * n, -1)
    loss = (y - target.double()).abs().mean()
    loss.backward()
    return [loss.detach(), p64.grad, q64.grad, *[x.grad for layer in mlp64 for x in layer.parameters()]]


@needs_native
def test_native_kernel_matches_float64_autograd():
    """An independent reference: the un-split MLP in float64 autograd on the concatenated batch."""
    p, q, mlp, target = problem(3, 5, 24, layers=3, seed=3)
    result = loss_and_grads(p, q, mlp, target, True, chunk_texels=8, workers=2)
    expected = float64_reference(p, q, mlp, target)
    for a, b in zip(result, expected):
        torch.testing.assert_close(a.double(), b, rtol=1e-4, atol=1e-6 * float(b.abs().max()))


def emulated_bf16(p, q, mlp, target, slope=0.01):
    """The bf16 kernel's arithmetic written out in float64: activations, layer weights and the
    gradients entering each product rounded to bfloat16 exactly where the kernel rounds them."""
    def bf(x):
        return x.float().to(torch.bfloat16).double()

    groups, images, hidden = q.shape
    n = p.shape[0] // groups
    weights = [bf(layer.weight.detach()) for layer in mlp]
    biases = [layer.bias.detach().double() for layer in mlp]
    pre = [(p.detach().view(groups, 1, n, hidden) + q.detach().view(groups, images, 1, hidden)).double()]
    acts = [bf(torch.where(pre[0] > 0, pre[0], slope * pre[0]))]
    for w, b in zip(weights[:-1], biases[:-1]):
        pre.append(acts[-1] @ w.T + b)
        acts.append(bf(torch.where(pre[-1] > 0, pre[-1], slope * pre[-1])))
    residual = acts[-1] @ weights[-1].T + biases[-1] - target.double().view(images, groups, n, -1).transpose(0, 1)
    count = target.numel()
    grads, d = [], torch.sign(residual)
    for k in range(len(weights) - 1, -1, -1):
        flat = d.reshape(-1, d.shape[-1])
        grads[:0] = [bf(flat).T @ acts[k].reshape(-1, hidden) / count, flat.sum(0) / count]
        d = (bf(d) @ weights[k]) * torch.where(pre[k] > 0, 1.0, slope)
    return [residual.abs().sum() / count, d.sum(1).reshape(-1, hidden) / count, d.sum(2) / count, *grads]


@needs_bf16
def test_bf16_kernel_equals_its_arithmetic_written_out():
    """bfloat16 products accumulated in float32 == the same roundings emulated in float64; and it is a
    different arithmetic from fp32 (loss within 1e-3, gradients within 10 %: bf16's 8-bit mantissa on
    sums of +-1 L1 gradients that largely cancel)."""
    p, q, mlp, target = problem(2, 16, 200, seed=5)
    bf16 = loss_and_grads(p, q, mlp, target, True, chunk_texels=64, workers=2, precision="bf16")
    for a, b in zip(bf16, emulated_bf16(p, q, mlp, target)):
        assert float((a.double() - b).norm() / b.norm()) < 1e-4
    fp32 = loss_and_grads(p, q, mlp, target, True, chunk_texels=64, workers=2)
    assert abs(float(bf16[0] - fp32[0])) < 1e-3 * float(fp32[0])
    errors = [float((a - b).norm() / b.norm()) for a, b in zip(bf16[1:], fp32[1:])]
    assert max(errors) < 0.1 and max(errors) > 1e-4, errors


def test_torch_fallback_without_native_kernel(monkeypatch):
    """No compiler / DYNBTF_NATIVE=0: fp32 runs on the PyTorch path, bf16 is refused with a reason."""
    monkeypatch.setattr(fused_mlp, "_native_library", lambda: None)
    assert native_precisions() == ()
    p, q, mlp, target = problem(1, 4, 20)
    loss = split_mlp_l1_loss(p, q, mlp, 0.01, target, precision="auto")
    loss.backward()
    assert torch.isfinite(loss) and p.grad is not None
    assert resolve_precision("auto") == "fp32"
    with pytest.raises(InputError, match="bf16"):
        resolve_precision("bf16")
    with pytest.raises(InputError, match="precision"):
        resolve_precision("fp16")


def test_precision_on_a_gpu_tensor_is_fp32():
    assert resolve_precision("auto", "cuda") == "fp32"
    with pytest.raises(InputError, match="GPU"):
        resolve_precision("bf16", "cuda")


def test_native_loader_reports_build_failures(tmp_path, monkeypatch):
    """A broken source or a disabled switch gives None and a status saying why, never an exception."""
    monkeypatch.setattr(native, "_SOURCE_DIR", tmp_path)
    monkeypatch.setenv("DYNBTF_NATIVE_CACHE", str(tmp_path / "cache"))
    (tmp_path / "broken_kernel.cpp").write_text("this is not C++\n")
    if native._compiler() is None:
        pytest.skip("no C++ compiler")
    assert native.load_library("broken_kernel") is None
    assert "failed" in native.status("broken_kernel")
    assert not list((tmp_path / "cache").glob("*.tmp"))  # nothing half-written left behind
    (tmp_path / "tiny_kernel.cpp").write_text('extern "C" int answer(void) { return 42; }\n')
    library = native.load_library("tiny_kernel")
    assert library is not None and library.answer() == 42
    assert len(list((tmp_path / "cache").glob("tiny_kernel-*.so"))) == 1
    monkeypatch.setenv("DYNBTF_NATIVE", "0")
    (tmp_path / "other_kernel.cpp").write_text('extern "C" int answer(void) { return 1; }\n')
    assert native.load_library("other_kernel") is None
    assert "DYNBTF_NATIVE=0" in native.status("other_kernel")


@needs_native
@pytest.mark.parametrize("hidden,out,layers,rows", [(32, 3, 3, 1000), (16, 1, 1, 7), (64, 5, 2, 130), (32, 16, 3, 64),
                                                    (48, 3, 4, 65), (128, 3, 2, 9)])
@pytest.mark.parametrize("activate_input", [False, True])
def test_native_inference_forward_matches_float64(hidden, out, layers, rows, activate_input):
    """The evaluation's forward (layers 2.. on rows of layer 1's activations) against the same layers in float64,
    to float32 rounding of sums of ``hidden`` products; tiles of 64 rows with tails, every template width."""
    g = torch.Generator().manual_seed(hidden + out + layers)
    mlp = [(torch.randn(hidden, hidden, generator=g) / hidden ** 0.5, torch.randn(hidden, generator=g))
           for _ in range(layers - 1)] + [(torch.randn(out, hidden, generator=g) / hidden ** 0.5,
                                            torch.randn(out, generator=g))]
    x = torch.randn(rows, hidden, generator=g)
    got = fused_mlp.native_mlp_forward(x, mlp, 0.01, activate_input=activate_input)
    y = x.double()
    y = torch.nn.functional.leaky_relu(y, 0.01) if activate_input else y
    for k, (w, b) in enumerate(mlp):
        y = y @ w.double().t() + b.double()
        if k < len(mlp) - 1:
            y = torch.nn.functional.leaky_relu(y, 0.01)
    assert got is not None and got.shape == (rows, out)
    torch.testing.assert_close(got.double(), y, rtol=1e-5, atol=1e-5 * float(y.abs().max()))


def test_native_inference_forward_declines_what_it_has_no_path_for():
    """Another dtype, a shape without a template instance, or a non-square hidden layer: None (torch answers)."""
    layers = [(torch.randn(32, 32), torch.randn(32)), (torch.randn(3, 32), torch.randn(3))]
    assert fused_mlp.native_mlp_forward(torch.randn(4, 32, dtype=torch.float64), layers, 0.01) is None
    assert fused_mlp.native_mlp_forward(torch.randn(4, 24), [(torch.randn(24, 24), torch.randn(24)),
                                                             (torch.randn(3, 24), torch.randn(3))], 0.01) is None
    assert fused_mlp.native_mlp_forward(torch.randn(4, 32), [(torch.randn(16, 32), torch.randn(16)),
                                                             (torch.randn(3, 16), torch.randn(3))], 0.01) is None


def test_texel_blocks_convert_every_float16_exactly():
    """The cache gather's float16 -> float32 conversion, its vector (F16C) path and its scalar path, equals NumPy's
    for all 65,536 bit patterns (NaNs stay NaN with their sign)."""
    import ctypes

    import numpy as np

    library = native.load_library("texel_blocks")
    if library is None:
        pytest.skip("no native kernel on this machine")
    halves = np.arange(65536, dtype=np.uint16)
    expected = halves.view(np.float16).astype(np.float32)
    nan = np.isnan(expected)
    scalar = np.empty(65536, np.float32)
    library.dynbtf_half_to_float(ctypes.c_void_p(halves.ctypes.data), ctypes.c_int64(65536),
                                 ctypes.c_void_p(scalar.ctypes.data))
    # one image of 65,536 one-channel texels, read as one block that starts at 40,000 and wraps at the end
    gathered = np.empty(65536, np.float32)
    rows, starts = np.zeros(1, np.int64), np.array([40000], np.int64)
    code = library.dynbtf_gather_blocks_f16(
        ctypes.c_void_p(halves.ctypes.data), ctypes.c_int64(1), ctypes.c_int64(65536), ctypes.c_int32(1),
        ctypes.c_void_p(rows.ctypes.data), ctypes.c_int64(1), ctypes.c_int64(1), ctypes.c_void_p(starts.ctypes.data),
        ctypes.c_int64(65536), ctypes.c_void_p(gathered.ctypes.data))
    assert code == 0
    gathered = np.roll(gathered, 40000)
    for converted in (scalar, gathered):
        assert np.array_equal(converted.view(np.uint32)[~nan], expected.view(np.uint32)[~nan])
        assert np.isnan(converted[nan]).all() and np.array_equal(np.signbit(converted), np.signbit(expected))
    bad_row = np.array([1], np.int64)  # outside the cache's one image: refused, nothing read
    assert library.dynbtf_gather_blocks_f16(
        ctypes.c_void_p(halves.ctypes.data), ctypes.c_int64(1), ctypes.c_int64(65536), ctypes.c_int32(1),
        ctypes.c_void_p(bad_row.ctypes.data), ctypes.c_int64(1), ctypes.c_int64(1),
        ctypes.c_void_p(starts.ctypes.data), ctypes.c_int64(16), ctypes.c_void_p(gathered.ctypes.data)) == 1


def triple_plane_problem(seed=0, side=16, groups=4, images=3, texels_per_group=24, texel_taps=None):
    """A perturbed Triple Plane, a step's texels (with repeats), its pairs' taps and targets 0.3 away from the
    float64 prediction. With ``texel_taps = J``, ``texels`` is ``(indices (J, N), weights (J, N))``: each row the
    weighted sum of J texels."""
    from dynbtf.representations.triple_plane import TriplePlane

    gen = torch.Generator().manual_seed(seed)
    model = TriplePlane(side, side, seed=seed)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.1 * torch.randn(p.shape, generator=gen))
    texels = torch.randint(0, side * side, (groups * texels_per_group,), generator=gen)
    if texel_taps is not None:
        texels = (torch.randint(0, side * side, (texel_taps, groups * texels_per_group), generator=gen),
                  torch.rand(texel_taps, groups * texels_per_group, generator=gen))
    directions = [nn.functional.normalize(torch.rand(groups * images, 3, generator=gen) + torch.tensor([0, 0, 0.3]),
                                          dim=-1) for _ in range(2)]
    taps = model.direction_taps(*directions)
    with torch.no_grad():
        predicted = reference_triple_plane_prediction(model.double(), texels, taps, images)
    model.float()
    sign = torch.randint(0, 2, predicted.shape, generator=gen) * 2 - 1
    return model, texels, taps, (predicted + 0.3 * sign).float()


def reference_triple_plane_prediction(model, texels, taps, images):
    """Written out independently in model's dtype: plane rows by advanced indexing, the taps' weighted sums, the
    un-split decoder on the concatenated inputs -> (B, G * n, 3)."""
    index, weight = taps
    groups = index.shape[0] // images
    angular_planes = torch.cat([model.f_h.reshape(-1, model.f_h.shape[-1]), model.f_d.reshape(-1, model.f_d.shape[-1])])
    angular = (angular_planes[index] * weight.to(angular_planes.dtype)[..., None]).sum(2).reshape(index.shape[0], -1)
    plane = model.f_u.reshape(-1, model.f_u.shape[-1])
    if isinstance(texels, tuple):  # (indices (J, N), weights (J, N)): weighted sums of texels
        features = sum(w.to(plane.dtype)[:, None] * plane[i] for i, w in zip(*texels))
    else:
        features = plane[texels]
    features = features.view(groups, 1, -1, model.f_u.shape[-1])
    n = features.shape[2]
    angular = angular.view(groups, images, 1, -1)
    x = torch.cat([features.expand(-1, images, -1, -1), angular.expand(-1, -1, n, -1)], -1)  # (G, B, n, in)
    layers = [model.decoder.first, *model.decoder.rest]
    for k, layer in enumerate(layers):
        x = layer(x)
        if k < len(layers) - 1:
            x = nn.functional.leaky_relu(x, model.decoder.negative_slope)
    return x.transpose(0, 1).reshape(images, -1, 3)


@needs_native
@pytest.mark.parametrize("workers, texel_taps", [(1, None), (2, None), (2, 4), (1, 1)])
def test_triple_plane_loss_in_native_kernels_matches_float64_autograd(workers, texel_taps):
    """The plane fetches and layer 1 in dynbtf_first_layer_forward / _backward, layers 2.. in the fused kernel: the
    loss and the gradient of every parameter equal float64 autograd of the written-out model, repeated texels
    included; with texel weights, each row the weighted sum of ``texel_taps`` texels (the sub-texel term's points)."""
    import copy

    model, texels, taps, target = triple_plane_problem(texel_taps=texel_taps)
    reference = copy.deepcopy(model).double()
    loss = reference_triple_plane_prediction(reference, texels, taps, target.shape[0]).sub(target.double()).abs().mean()
    loss.backward()
    angular_planes = torch.cat([model.f_h.reshape(-1, 8), model.f_d.reshape(-1, 8)])
    indices, weights = texels if texel_taps else (texels, None)
    native_loss = fused_mlp.triple_plane_l1_loss(model.f_u.reshape(-1, 16), indices, angular_planes, taps,
                                                 model.decoder.first, model.decoder.rest, 0.01, target,
                                                 chunk_texels=8, workers=workers, texel_weights=weights)
    assert native_loss is not None, "the native kernels should take a CPU float32 Triple Plane"
    native_loss.backward()
    torch.testing.assert_close(native_loss.double(), loss.detach(), rtol=1e-5, atol=0)
    for (name, p), (_, q) in zip(model.named_parameters(), reference.named_parameters()):
        scale = float(q.grad.abs().max())
        torch.testing.assert_close(p.grad.double(), q.grad, rtol=1e-4, atol=1e-5 * scale, msg=name)


@needs_native
def test_triple_plane_loss_takes_the_native_kernels_in_a_fit_step_and_equals_the_torch_path():
    """TriplePlane.texel_image_l1_loss with taps (what the fit calls) goes through the native kernels, and its
    gradients equal the torch path's (the fetched features and decoder_l1_loss) to float rounding."""
    import copy

    model, texels, taps, target = triple_plane_problem(seed=1)
    torch_path = copy.deepcopy(model)
    calls = []
    real = fused_mlp._TriplePlaneL1.apply
    w = torch.zeros(taps[0].shape[0], 3)  # (directions are not read when taps are given)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(fused_mlp._TriplePlaneL1, "apply", lambda *a: calls.append(1) or real(*a))
        model.texel_image_l1_loss(w, w, target, texels, chunk_texels=8, workers=2, texel_groups=4,
                                  angular_taps=taps).backward()
    assert calls == [1]
    features = torch_path.f_u.reshape(-1, 16)[texels]
    torch_path.decoder.texel_image_l1_loss(features, torch_path.angular_features(w, w, taps), target, chunk_texels=8,
                                           workers=2, texel_groups=4).backward()
    for (name, p), (_, q) in zip(model.named_parameters(), torch_path.named_parameters()):
        torch.testing.assert_close(p.grad, q.grad, rtol=1e-4, atol=1e-6 * float(q.grad.abs().max()), msg=name)


@needs_native
def test_triple_plane_loss_declines_or_refuses_what_its_kernels_do_not_take():
    model, texels, taps, target = triple_plane_problem(seed=2)
    angular_planes = torch.cat([model.f_h.reshape(-1, 8), model.f_d.reshape(-1, 8)])
    args = (model.decoder.first, model.decoder.rest, 0.01)
    double = copy_double(model)
    assert fused_mlp.triple_plane_l1_loss(double.f_u.reshape(-1, 16), texels, angular_planes.double(), taps,
                                          double.decoder.first, double.decoder.rest, 0.01, target.double()) is None
    outside = texels.clone()
    outside[5] = 16 * 16  # one past the plane's last texel
    with pytest.raises(InputError, match="texel or angular tap index outside its plane"):
        fused_mlp.triple_plane_l1_loss(model.f_u.reshape(-1, 16), outside, angular_planes, taps, *args, target)
    with pytest.raises(InputError, match="first layer takes 32 inputs"):
        fused_mlp.triple_plane_l1_loss(model.f_u.reshape(-1, 16)[:, :15], texels, angular_planes, taps, *args, target)
    with pytest.raises(InputError, match=r"texel_weights: expected \(J, N\) with texels int64 of the same shape"):
        fused_mlp.triple_plane_l1_loss(model.f_u.reshape(-1, 16), texels, angular_planes, taps, *args, target,
                                       texel_weights=torch.ones(2, texels.shape[0]))
    outside = torch.stack([texels, texels])
    outside[1, 3] = -1
    with pytest.raises(InputError, match="texel or angular tap index outside its plane"):
        fused_mlp.triple_plane_l1_loss(model.f_u.reshape(-1, 16), outside, angular_planes, taps, *args, target,
                                       texel_weights=torch.ones(outside.shape))


def copy_double(model):
    import copy

    return copy.deepcopy(model).double()
