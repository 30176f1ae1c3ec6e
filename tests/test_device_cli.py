"""``--device`` of ``dynbtf synth`` and ``dynbtf demo`` and ``synthesized_btf(device=...)``: the resolver of ``fit``.

This machine has no GPU: ``--device cpu`` runs, ``--device cuda`` is refused with
:func:`dynbtf.device.resolve_device`'s error before any work, ``auto`` is the CPU,
and ``auto`` is passed on as CUDA when torch reports it present (checked by
pretending it is, up to where the model would be loaded).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from dynbtf.cli.main import main
from dynbtf.device import resolve_device
from dynbtf.errors import InputError
from dynbtf.representations.model_file import save_model
from dynbtf.representations.triple_plane import TriplePlane
from dynbtf.synthesized import synthesized_btf

pytestmark = pytest.mark.usefixtures("single_thread")
no_cuda = pytest.mark.skipif(torch.cuda.is_available(), reason="checks the behaviour without CUDA")
CUDA_ABSENT = "'cuda' requested but CUDA is not available here; use 'cpu' or 'auto'"


@pytest.fixture(scope="module")
def model():
    return TriplePlane(16, 16, positional_channels=4, angular_channels=2, hidden=8, seed=3)


@pytest.fixture(scope="module")
def model_file(model, tmp_path_factory):
    return save_model(tmp_path_factory.mktemp("device") / "m.dbtfm", model)


@no_cuda
def test_auto_is_the_cpu_here(model_file):
    assert resolve_device("auto") == torch.device("cpu")
    btf = synthesized_btf(model_file, "hist", device="auto")
    assert btf.device.type == "cpu" and btf.decode_path.fused  # the CPU's numba fast path


def test_synthesized_btf_device_cpu(model, model_file):
    uv = np.array([[0.25, 0.5], [1e6 + 0.25, 0.5]])
    w = np.array([[0.0, 0.0, 1.0]] * 2)
    on_cpu = synthesized_btf(model, "hist", scale=4.0, device="cpu")
    assert on_cpu.model is model  # already there: not copied
    from_file = synthesized_btf(model_file, "hist", scale=4.0, device=torch.device("cpu"))
    np.testing.assert_array_equal(on_cpu.eval(uv, w, w), synthesized_btf(model, "hist", scale=4.0).eval(uv, w, w))
    np.testing.assert_array_equal(from_file.eval(uv, w, w), on_cpu.eval(uv, w, w))


@no_cuda
@pytest.mark.parametrize("where", ["model", "file"])
def test_synthesized_btf_device_cuda_is_refused(model, model_file, where):
    with pytest.raises(InputError, match=CUDA_ABSENT):
        synthesized_btf(model if where == "model" else model_file, "hist", device="cuda")
    with pytest.raises(InputError, match="not a valid torch device"):
        synthesized_btf(model, "hist", device="gpu")
    assert model.positional_plane().device.type == "cpu"


@pytest.mark.parametrize("device", [[], ["--device", "cpu"], ["--device", "auto"]])
def test_synth_device_cpu_writes_the_image(model_file, tmp_path, capsys, device):
    out = tmp_path / "s.png"
    assert main(["synth", str(model_file), "--resolution", "8", "-o", str(out), *device]) == 0
    assert out.is_file() and "wrote" in capsys.readouterr().out


@no_cuda
def test_synth_device_cuda_is_refused_before_any_work(model_file, tmp_path, capsys):
    out = tmp_path / "s.png"
    assert main(["synth", str(model_file), "--resolution", "8", "-o", str(out), "--device", "cuda"]) == 2
    assert capsys.readouterr().err == f"dynbtf: error: device: {CUDA_ABSENT}\n" and not out.exists()


def test_synth_device_auto_asks_for_cuda_when_present(model_file, tmp_path, monkeypatch, capsys):
    import dynbtf.representations.model_file as model_file_module

    asked = []

    def load_model(path, device=None):
        asked.append(device)
        raise InputError("stopped where the model would be loaded")

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(model_file_module, "load_model", load_model)
    assert main(["synth", str(model_file), "--resolution", "8", "-o", str(tmp_path / "s.png")]) == 2
    assert asked == [torch.device("cuda")] and "stopped where" in capsys.readouterr().err


def test_demo_command_passes_device(monkeypatch, tmp_path):
    import dynbtf.demo

    configs = []
    monkeypatch.setattr(dynbtf.demo, "run_demo", lambda config, **kw: configs.append(config))
    assert main(["demo", "-o", str(tmp_path / "a"), "--device", "cpu"]) == 0
    assert main(["demo", "-o", str(tmp_path / "b")]) == 0
    assert [c.device for c in configs] == ["cpu", "auto"]


@no_cuda
def test_demo_device_cuda_is_refused_before_any_stage(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "-o", str(out), "--quick", "--size", "16", "--device", "cuda"]) == 2
    assert capsys.readouterr().err == f"dynbtf: error: device: {CUDA_ABSENT}\n" and not out.exists()


@no_cuda
def test_demo_device_reaches_training_and_the_model(tmp_path, monkeypatch):
    import importlib

    import dynbtf.representations.model_file as model_file_module
    from dynbtf.demo import DemoConfig, run_demo

    fit_module = importlib.import_module("dynbtf.training.fit")  # the module (dynbtf.training.fit is also a function)

    fit_devices, load_devices = [], []
    real_fit, real_load = fit_module.fit, model_file_module.load_model

    def fit(rep, source, config, *args, **kwargs):
        fit_devices.append(config.device)
        return real_fit(rep, source, config, *args, **kwargs)

    def load_model(path, device=None):
        load_devices.append(device)
        rep, meta = real_load(path, device=device)
        assert rep.positional_plane().device.type == "cpu"
        return rep, meta

    monkeypatch.setattr(fit_module, "fit", fit)
    monkeypatch.setattr(model_file_module, "load_model", load_model)
    stages = ("data", "fit", "evaluate")
    logs: list[str] = []
    run_demo(DemoConfig(output=str(tmp_path), size=16, quick=True, device="cpu"), progress=False, log=logs.append,
             stages=stages)
    assert fit_devices == ["cpu"] and load_devices == ["cpu"]
    assert json.loads((tmp_path / "stages" / "evaluate.json").read_text())["n_pairs"] > 0
    # the device is how to run, not what: finished stages are reused with another one
    logs.clear()
    run_demo(DemoConfig(output=str(tmp_path), size=16, quick=True, device="auto"), progress=False, log=logs.append,
             stages=stages)
    assert sum("skipped" in line for line in logs) == len(stages) and fit_devices == ["cpu"]
