"""``dynbtf render``: a tiny render through the command line, and clear errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("mitsuba")


@pytest.fixture(scope="module")
def small_model(tmp_path_factory):
    from dynbtf.representations.model_file import save_model
    from dynbtf.representations.triple_plane import TriplePlane

    model = TriplePlane(16, 16, positional_channels=4, angular_channels=2, hidden=8, seed=1)
    with torch.no_grad():
        model.decoder.rest[-1].bias.add_(0.5)
    path = tmp_path_factory.mktemp("cli") / "small.dbtfm"
    save_model(path, model)
    return path


@pytest.mark.mitsuba
def test_render_command_writes_png_and_exr(small_model, tmp_path, capsys):
    from dynbtf.cli.main import main
    from dynbtf.io import load_image

    png, exr = tmp_path / "plane.png", tmp_path / "sphere.exr"
    assert main(["render", str(small_model), "--scene", "plane", "--method", "hist", "--scale", "4",
                 "--size", "32", "--spp", "2", "-o", str(png)]) == 0
    assert main(["render", str(small_model), "--scene", "sphere", "--lighting", "point", "--method", "tile",
                 "--size", "32", "--spp", "2", "-o", str(exr)]) == 0
    a, b = load_image(png), load_image(exr)
    assert a.shape == b.shape == (32, 32, 3)
    assert np.isfinite(b).all() and b.max() > 0.0 and a.std() > 0.0
    assert "kernel compilation" in capsys.readouterr().out


@pytest.mark.parametrize("args, message", [
    (["--scene", "teapot"], "--scene: expected one of"),
    (["--lighting", "moon"], "--lighting: expected one of"),
    (["--method", "quilt"], "--method: expected one of"),
    (["--scale", "-1"], "--scale"),
])
def test_render_command_bad_options(small_model, tmp_path, capsys, args, message):
    from dynbtf.cli.main import main

    assert main(["render", str(small_model), "-o", str(tmp_path / "x.png"), *args]) == 2
    assert message in capsys.readouterr().err


def test_render_command_missing_model(tmp_path, capsys):
    from dynbtf.cli.main import main

    assert main(["render", str(tmp_path / "none.dbtfm"), "-o", str(tmp_path / "x.png")]) == 2
    assert "model file not found" in capsys.readouterr().err
