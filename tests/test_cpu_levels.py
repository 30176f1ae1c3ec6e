"""Instruction-set levels (dynbtf.cpu): detection, forcing a lower level on every library, and the native kernels
built per level computing the same numbers (to float32 rounding) on each level this CPU runs."""

import os
import subprocess
import sys

import pytest
import torch
from torch import nn

from dynbtf import cpu
from dynbtf.decoder import fused_mlp, native
from dynbtf.errors import InputError

from test_native_kernel import float64_reference


def test_levels_from_cpu_flags():
    avx2 = frozenset({"sse2", "avx", "avx2", "fma", "f16c", "bmi2"})
    avx512 = avx2 | {"avx512f", "avx512bw", "avx512dq", "avx512vl", "avx512cd"}
    assert cpu.hardware_isa(frozenset({"sse2", "avx"})) == "portable"
    assert cpu.hardware_isa(avx2 - {"fma"}) == "portable"  # AVX2 without FMA is not x86-64-v3
    assert cpu.hardware_isa(avx2) == "avx2"
    assert cpu.hardware_isa(avx512) == "avx512"
    assert cpu.hardware_isa(avx512 | {"avx512_bf16"}) == "avx512bf16"
    assert cpu.hardware_isa(avx2 | {"avx512_bf16"}) == "avx2"  # bf16 without AVX-512F: no bf16 level
    assert [cpu.vector_width(isa) for isa in cpu.ISAS] == [4, 8, 16, 16]


def test_forcing_a_level_checks_it(monkeypatch):
    monkeypatch.setattr(cpu, "hardware_isa", lambda features=None: "avx2")
    monkeypatch.setenv(cpu.ISA_ENV, "avx512")
    with pytest.raises(InputError, match="DYNBTF_CPU_ISA=avx512: this CPU .* runs at most 'avx2'"):
        cpu.active_isa()
    monkeypatch.setenv(cpu.ISA_ENV, "sse9")
    with pytest.raises(InputError, match="DYNBTF_CPU_ISA='sse9': expected one of portable, avx2, avx512"):
        cpu.active_isa()
    monkeypatch.setenv(cpu.ISA_ENV, "portable")
    assert cpu.active_isa() == "portable"
    monkeypatch.setenv(cpu.ISA_ENV, "auto")
    assert cpu.active_isa() == "avx2"
    env = cpu.isa_environment("avx2")
    if cpu._is_x86():
        assert env["ATEN_CPU_CAPABILITY"] == "avx2" and env["MKL_ENABLE_INSTRUCTIONS"] == "AVX2"
        assert env["NUMBA_CPU_NAME"] == "haswell" and env["MKL_CBWR"] == "AVX2,STRICT"
        # torch.compile's kernels of each level in a cache of their own (Inductor's keys do not tell levels apart)
        caches = {level: cpu.isa_environment(level)["TORCHINDUCTOR_CACHE_DIR"] for level in cpu.ISAS}
        assert len(set(caches.values())) == len(cpu.ISAS) and caches["avx2"] == cpu.inductor_cache_dir("avx2")


def test_a_level_above_the_cpu_is_refused_before_its_code_runs(monkeypatch):
    monkeypatch.setattr(cpu, "hardware_isa", lambda features=None: "portable")
    with pytest.raises(InputError, match="runs at most 'portable'"):
        native.load_library("fused_mlp", "avx2")


@pytest.mark.skipif(cpu.hardware_isa() in ("portable", "avx2"), reason="needs a CPU above AVX2 to force AVX2")
def test_forcing_avx2_reaches_torch_mkl_and_numba():
    code = ("import os, dynbtf, torch, numba; from dynbtf.cpu import active_isa, isa_description; "
            "print(active_isa(), torch.backends.cpu.get_cpu_capability(), os.environ['MKL_ENABLE_INSTRUCTIONS'], "
            "numba.config.CPU_NAME, os.path.basename(os.environ['TORCHINDUCTOR_CACHE_DIR']).split('-', 1)[1])")
    env = {k: v for k, v in os.environ.items() if k not in cpu.isa_environment("avx2")} | {cpu.ISA_ENV: "avx2"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    assert out.split() == ["avx2", "AVX2", "AVX2", "haswell", "dynbtf-avx2"]
    # torch at work before dynbtf could tell it (ATen picks its kernels at its first operation): the mismatch is
    # named, not silently measured
    late = "import torch; torch.ones(2) + 1; import dynbtf.cpu as c; print(c.check_forced_environment())"
    out = subprocess.run([sys.executable, "-c", late], env=env, capture_output=True, text=True, check=True).stdout
    assert "PyTorch was loaded before dynbtf" in out and "ATEN_CPU_CAPABILITY=avx2" in out


def _problem(seed=0, groups=8, images=16, texels=70):
    g = torch.Generator().manual_seed(seed)
    p = torch.randn(groups * texels, 32, generator=g)
    q = torch.randn(groups, images, 32, generator=g)
    torch.manual_seed(seed)
    mlp = [nn.Linear(32, 32), nn.Linear(32, 32), nn.Linear(32, 3)]
    target = torch.randn(images, groups * texels, 3, generator=g)
    return p, q, mlp, target


@pytest.mark.parametrize("isa", [isa for isa in cpu.ISAS if cpu.ISAS.index(isa) <= cpu.ISAS.index(cpu.hardware_isa())])
def test_every_level_the_cpu_runs_computes_the_same_loss_and_gradients(isa, monkeypatch):
    """The kernel of each level against the float64 autograd reference, to float32 rounding of sums of 32 products
    (the levels differ in vector width, register blocks and FMA contraction, not in what they compute); and for
    one level, the same bits whatever the number of threads (each item's gradients summed in item order)."""
    load = native.load_library
    assert load("fused_mlp", isa) is not None, native.status("fused_mlp", isa)
    monkeypatch.setattr(native, "load_library", lambda name, level=None: load(name, isa))  # this level's kernel
    assert fused_mlp._native_supports(torch.zeros(1, 32), [torch.zeros(32, 32), torch.zeros(3, 32)], "fp32")
    p, q, mlp, target = _problem()
    results = []
    for workers in (1, 2, 3):
        pp, qq = p.clone().requires_grad_(), q.clone().requires_grad_()
        for layer in mlp:
            layer.zero_grad()
        loss = fused_mlp.split_mlp_l1_loss(pp, qq, mlp, 0.01, target, chunk_texels=32, workers=workers)
        loss.backward()
        results.append([loss.detach(), pp.grad, qq.grad, *[t.grad.clone() for layer in mlp for t in layer.parameters()]])
    for other in results[1:]:
        assert all(torch.equal(a, b) for a, b in zip(results[0], other))
    expected = float64_reference(p, q, mlp, target)  # the un-split MLP by float64 autograd
    eps = float(torch.finfo(torch.float32).eps)
    for got, want in zip(results[0], expected):
        # a gradient sums sign(residual) x products over 8,960 samples: float32 rounding of such sums
        torch.testing.assert_close(got.double(), want, rtol=64 * eps, atol=64 * eps * float(want.abs().max()))


def test_fma_peak_is_measured_on_each_level():
    for isa in cpu.ISAS[:cpu.ISAS.index(cpu.hardware_isa()) + 1]:
        peak = native.fma_peak_flops(isa, threads=1, seconds=0.05)
        assert peak is not None and peak > 1e8, isa
