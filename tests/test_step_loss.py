"""The step's loss compiled by torch.compile against the eager fused kernels, and the compile option's errors."""

import copy

import pytest
import torch

from dynbtf.cli.main import main
from dynbtf.errors import InputError
from dynbtf.representations.triple_plane import TriplePlane
from dynbtf.training.step_loss import StepLoss, resolve_compile


def _structured_model() -> TriplePlane:
    torch.manual_seed(0)
    model = TriplePlane(8, 8, seed=1)
    with torch.no_grad():  # values of order one (a fresh model's planes are near zero)
        for p in model.parameters():
            p.add_(0.3 * torch.randn_like(p))
    return model


def test_compiled_step_loss_equals_the_eager_fused_kernels_with_their_gradients():
    """compile="kernels" traces the decoder as ordinary ops and lets autograd and Inductor make the backward pass;
    the eager path runs the native fused kernels with their hand-written one. Loss and every parameter's gradient
    agree to float32 rounding of sums over a few hundred samples."""
    model = _structured_model()
    groups, images = 4, 3
    g = torch.Generator().manual_seed(2)
    up = torch.tensor([0.0, 0.0, 1.0])
    w_view = torch.nn.functional.normalize(torch.rand(groups * images, 3, generator=g) + up, dim=-1)
    w_light = torch.nn.functional.normalize(torch.rand(groups * images, 3, generator=g) + up, dim=-1)
    target = torch.rand(images, 64, 3, generator=g)
    taps = model.direction_taps(w_view, w_light)
    neighbours = torch.randint(0, 64, (4, 20), generator=g)
    weights = torch.rand(4, 20, generator=g)
    weights /= weights.sum(0)
    results = {}
    for mode in ("off", "kernels"):
        m = copy.deepcopy(model)
        step = StepLoss(m, compile=mode)
        loss = step.batch(w_view, w_light, target, None, texel_groups=groups, angular_taps=taps) + \
            step.between_texels(neighbours, weights, w_view[:images], w_light[:images], target[:, :20],
                                tuple(t[:images] for t in taps))
        loss.backward()
        results[mode] = (float(loss.detach()), {n: p.grad.clone() for n, p in m.named_parameters()})
    assert results["kernels"][0] == pytest.approx(results["off"][0], rel=1e-5)
    for name, eager in results["off"][1].items():
        compiled = results["kernels"][1][name]
        assert float(eager.abs().max()) > 0, name
        assert float((compiled - eager).abs().max()) <= 1e-5 * float(eager.abs().max()), name


def test_compile_modes_are_checked():
    assert resolve_compile("auto", "cpu") == "off"
    with pytest.raises(InputError, match="--compile .*expected one of 'auto', 'off', 'kernels' or 'graphs'|"
                                         "--compile \\(TrainConfig.compile\\): expected one of"):
        resolve_compile("fast", "cpu")
    with pytest.raises(InputError, match="a compiled loss computes in float32"):
        StepLoss(TriplePlane(4, 4), compile="kernels", precision="bf16")
    with pytest.raises(InputError, match="resolved"):
        StepLoss(TriplePlane(4, 4), compile="auto")


def test_fit_command_names_the_compile_option_it_cannot_use(tmp_path, capsys):
    out = tmp_path / "m.dbtfm"
    code = main(["fit", "sim:leather?size=8", "-o", str(out), "--device", "cpu", "--compile", "graphs"])
    captured = capsys.readouterr()
    assert code != 0
    assert "--compile graphs: CUDA graphs need a CUDA device, got 'cpu'; use kernels or off" in captured.err
    assert "recipe" not in captured.out and not out.exists()
    code = main(["fit", "sim:leather?size=8", "-o", str(out), "--compile", "fast"])
    assert code != 0 and "--compile (TrainConfig.compile): expected 'auto', 'off', 'kernels' or 'graphs', got " \
        "'fast'" in capsys.readouterr().err


@pytest.mark.parametrize("device, mode", [
    ("cpu", "kernels"),
    pytest.param("cuda", "kernels", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")),
    pytest.param("cuda", "graphs", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA"))])
def test_compiled_steps_train_as_the_eager_ones(device, mode):
    """Five optimizer steps from the same start and batches, eager and compiled (on a GPU also replayed as CUDA
    graphs step after step, gradients cleared as the fit does): the losses and the final parameters agree to float32
    rounding. (SGD: its update is linear in the gradient, so rounding stays rounding.)"""
    model = _structured_model().to(device)
    groups, images = 4, 3
    g = torch.Generator().manual_seed(3)
    up = torch.tensor([0.0, 0.0, 1.0])
    batches = []
    for _ in range(5):
        w_view = torch.nn.functional.normalize(torch.rand(groups * images, 3, generator=g) + up, dim=-1)
        w_light = torch.nn.functional.normalize(torch.rand(groups * images, 3, generator=g) + up, dim=-1)
        batches.append((w_view.to(device), w_light.to(device), torch.rand(images, 64, 3, generator=g).to(device)))
    runs = {}
    for which in ("off", mode):
        m = copy.deepcopy(model)
        optimizer = torch.optim.SGD(m.parameters(), lr=0.1)
        step = StepLoss(m, compile=which)
        losses = []
        for w_view, w_light, target in batches:
            optimizer.zero_grad(set_to_none=True)
            step.begin_step()
            loss = step.batch(w_view, w_light, target, None, texel_groups=groups,
                              angular_taps=m.direction_taps(w_view, w_light))
            loss.backward()
            losses.append(float(loss.detach()))
            optimizer.step()
        runs[which] = (losses, {n: p.detach().clone() for n, p in m.named_parameters()})
    assert runs["off"][0][-1] < runs["off"][0][0]  # the steps learn
    assert runs[mode][0] == pytest.approx(runs["off"][0], rel=1e-5)
    for name, eager in runs["off"][1].items():
        assert float((runs[mode][1][name] - eager).abs().max()) <= 1e-5 * float(eager.abs().max()), name


def test_auto_compiles_on_a_gpu_only_the_kinds_measured_to_pay(monkeypatch):
    """--compile auto: CUDA graphs for the Triple Plane on a GPU with Triton; the parallax model (its march would be
    traced step by step) and a GPU without Triton stay eager; the CPU stays on its native kernels."""
    from dynbtf.representations.parallax import ParallaxTriplePlane
    from dynbtf.training import step_loss

    triple, parallax = TriplePlane(4, 4), ParallaxTriplePlane(4, 4)
    monkeypatch.setattr(step_loss, "_has_triton", lambda: True)
    assert resolve_compile("auto", "cuda", triple) == "graphs" == resolve_compile("auto", "cuda")
    assert resolve_compile("auto", "cuda", parallax) == "off"
    assert resolve_compile("graphs", "cuda", parallax) == "graphs"  # asked for: done
    assert resolve_compile("auto", "cpu", triple) == "off"
    monkeypatch.setattr(step_loss, "_has_triton", lambda: False)
    assert resolve_compile("auto", "cuda", triple) == "off"
    with pytest.raises(InputError, match="--compile kernels: torch.compile needs Triton on a GPU"):
        resolve_compile("kernels", "cuda", triple)
