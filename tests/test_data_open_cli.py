"""open_btf dispatch, sim: specs, and the info / convert / show commands (via dynbtf.cli.main.main)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from dynbtf.cli.main import main
from dynbtf.data import (ArrayBTF, StoredBTF, UBO2003BTF, UBO2014BTF, open_btf, parse_sim_spec, sniff_format,
                         write_stored, write_ubo2003, write_ubo2014)
from dynbtf.data.directions import ubo2003_directions
from dynbtf.errors import FormatError, InputError
from dynbtf.io import load_image


def small_source(seed=0) -> ArrayBTF:
    rng = np.random.default_rng(seed)
    dirs, _ = ubo2003_directions()
    return ArrayBTF(rng.uniform(0.05, 0.9, (3, 4, 5, 6, 3)), dirs[[0, 7, 30]], dirs[[1, 19, 40, 80]], name="small")


@pytest.fixture
def files(tmp_path):
    src = small_source()
    return {
        "src": src,
        "btf": write_ubo2014(tmp_path / "a.btf", src, components=100, scalar="float"),
        "zip": write_ubo2003(tmp_path / "a.zip", src, image_format="png"),
        "dbtf": write_stored(tmp_path / "a.dbtf", src, dtype="float32", progress=False),
    }


def test_open_btf_dispatches_on_content_not_name(files, tmp_path):
    assert sniff_format(files["btf"]) == "ubo2014" and type(open_btf(files["btf"])) is UBO2014BTF
    assert sniff_format(files["zip"]) == "ubo2003" and type(open_btf(files["zip"])) is UBO2003BTF
    assert sniff_format(files["dbtf"]) == "stored" and type(open_btf(files["dbtf"])) is StoredBTF
    assert type(open_btf(files["dbtf"] / "meta.json")) is StoredBTF
    renamed = tmp_path / "data.bin"
    renamed.write_bytes(files["btf"].read_bytes())
    assert type(open_btf(renamed)) is UBO2014BTF
    src = files["src"]
    for key in ("btf", "dbtf"):
        np.testing.assert_allclose(open_btf(files[key]).image(2, 3), src.image(2, 3), atol=1e-5)
    assert open_btf(src) is src


def test_open_btf_errors(tmp_path):
    with pytest.raises(FormatError, match="not found"):
        open_btf(tmp_path / "missing.btf")
    junk = tmp_path / "junk.dat"
    junk.write_bytes(b"\x00\x01 nothing we know")
    with pytest.raises(FormatError, match="unrecognized format"):
        open_btf(junk)
    with pytest.raises(FormatError, match="without meta.json"):
        open_btf(tmp_path)


def test_parse_sim_spec():
    assert parse_sim_spec("sim:leather") == ("leather", {"size": 128, "grid": "ubo2003", "seed": 0, "relief": 1.0})
    assert parse_sim_spec("sim:stone?size=32&grid=ubo2014&seed=7&relief=0.5") == (
        "stone", {"size": 32, "grid": "ubo2014", "seed": 7, "relief": 0.5})
    with pytest.raises(InputError, match="unknown option 'colour'"):
        parse_sim_spec("sim:stone?colour=red")
    with pytest.raises(InputError, match="'size' must be an integer"):
        parse_sim_spec("sim:stone?size=big")
    with pytest.raises(InputError, match="sim:<material>"):
        parse_sim_spec("sim:")
    with pytest.raises(InputError, match="option 'size' is given twice"):  # not the last one, silently
        parse_sim_spec("sim:stone?size=64&size=8")


def test_open_simulated_spec():
    btf = open_btf("sim:leather?size=8&seed=1")
    assert btf.shape == (81, 81, 8, 8)
    np.testing.assert_allclose(btf.views, ubo2003_directions()[0], atol=1e-12)
    with pytest.raises(InputError):
        open_btf("sim:no_such_material?size=8")


# ------------------------------------------------------------------ command line
def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_info(files, capsys):
    code, out, err = run(capsys, "info", files["btf"])
    assert code == 0, err
    assert "ubo2014-dfmf" in out and "5 x 6 texels" in out and "views      3" in out and "lights     4" in out
    assert "colour_model=0" in out and "components=[12, 12, 12]" in out and "scalar_bytes=4" in out
    code, out, _ = run(capsys, "info", files["dbtf"], "--json", "--images", "12")
    s = json.loads(out)
    src = files["src"]
    all_values = src.values
    assert s["images_sampled"] == 12 and s["n_images"] == 12
    assert s["value_range_sampled"][0] == pytest.approx(float(all_values.min()), abs=1e-6)
    assert s["value_range_sampled"][1] == pytest.approx(float(all_values.max()), abs=1e-6)
    assert s["view_theta_range_deg"] == pytest.approx([0.0, 45.0])
    assert s["raw_float32_bytes"] == 12 * 5 * 6 * 3 * 4 and s["bytes_on_disk"] > s["raw_float32_bytes"]
    assert s["details"]["dtype"] == "float32" and s["details"]["provenance.source_kind"] == "ArrayBTF"


def test_convert_and_show(files, tmp_path, capsys):
    out_dir = tmp_path / "c.dbtf"
    code, out, err = run(capsys, "convert", files["zip"], "-o", out_dir, "--dtype", "float32", "--quiet")
    assert code == 0, err
    converted, original = StoredBTF(out_dir), UBO2003BTF(files["zip"])
    np.testing.assert_array_equal(converted.image(1, 2), original.image(1, 2))
    # show: nearest direction by angles, by index; PNG (sRGB 8-bit) and EXR (linear)
    code, out, err = run(capsys, "show", out_dir, "--view", "29,2", "--light", "2", "-o", tmp_path / "a.exr")
    assert code == 0, err
    v = 1  # the views are (0, 0), (30, 0), (45, 220) deg: (30, 0) is the nearest to (29, 2)
    assert "view 1 (theta 30.0, phi 0.0 deg)" in out
    np.testing.assert_allclose(load_image(tmp_path / "a.exr"), converted.image(v, 2), atol=1e-6)
    code, _, err = run(capsys, "show", out_dir, "--view", "0", "--light", "0", "-o", tmp_path / "a.png",
                       "--exposure", "0.5")
    assert code == 0, err
    np.testing.assert_allclose(load_image(tmp_path / "a.png"), converted.image(0, 0) * 0.5, atol=0.01)
    code, _, err = run(capsys, "show", out_dir, "--view", "0", "--light", "2", "--cosine", "-o", tmp_path / "c.exr")
    assert code == 0, err
    np.testing.assert_allclose(load_image(tmp_path / "c.exr"), converted.image(0, 2) * converted.lights[2, 2],
                               rtol=1e-6)


def test_convert_to_the_exchange_formats(files, tmp_path, capsys):
    src = files["src"]
    code, out, err = run(capsys, "convert", files["dbtf"], "-o", tmp_path / "x.btf", "--components", "12",
                         "--scalar", "float")
    assert code == 0 and "UBO2014 DFMF, 12 components, float" in out, err
    np.testing.assert_allclose(open_btf(tmp_path / "x.btf").image(2, 1), src.image(2, 1), atol=1e-5)
    code, out, err = run(capsys, "convert", files["btf"], "-o", tmp_path / "x.zip")
    assert code == 0, err
    zipped = open_btf(tmp_path / "x.zip")
    assert type(zipped) is UBO2003BTF and zipped.shape == src.shape
    code, _, err = run(capsys, "convert", files["btf"], "-o", tmp_path / "x.zip")
    assert code == 2 and "already exists" in err


@pytest.mark.parametrize("argv, message", [
    (["info", "{tmp}/missing.btf"], "missing.btf: not found"),
    (["show", "{btf}", "--view", "abc", "--light", "0", "-o", "{tmp}/x.png"], "--view: expected an index"),
    (["show", "{btf}", "--view", "99", "--light", "0", "-o", "{tmp}/x.png"], "--view: index 99 out of range"),
    (["show", "{btf}", "--view", "0", "--light", "95,0", "-o", "{tmp}/x.png"], "theta must be 0..90"),
    (["show", "{btf}", "--view", "0", "--light", "0", "-o", "{tmp}/x.gif"], "unsupported image extension"),
    (["show", "{btf}", "--view", "0", "--light", "0", "-o", "{tmp}/x.png", "--exposure", "-1"], "--exposure"),
    (["convert", "{btf}", "-o", "{dbtf}"], "already exists"),
    (["convert", "{btf}", "-o", "{tmp}/n.dbtf", "--dtype", "int8"], "dtype"),
    (["convert", "{btf}", "-o", "{tmp}/n.btf", "--scalar", "quad"], "scalar"),
    (["info", "sim:stone?size=abc"], "'size' must be an integer"),
    (["fit", "{btf}", "-o", "{tmp}/m.dbtfm", "--lr-scale", "-1"], "--lr-scale (TrainConfig.lr_scale): expected a "
                                                                  "finite number in (0, 1000000], got -1.0"),
    (["synth", "{dbtf}", "-o", "{tmp}/s.png"], "is a BTF (stored), not a model file"),
    (["synth", "{btf}", "-o", "{tmp}/s.png"], "is a BTF (ubo2014), not a model file"),
])
def test_user_errors_are_one_line_with_status_2(files, tmp_path, capsys, argv, message):
    argv = [a.format(tmp=tmp_path, btf=files["btf"], dbtf=files["dbtf"]) for a in argv]
    code, out, err = run(capsys, *argv)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("dynbtf: error: ") and message in lines[0], err


def test_corrupt_file_through_the_command_line(files, tmp_path, capsys):
    bad = tmp_path / "bad.btf"
    bad.write_bytes(files["btf"].read_bytes()[:500])
    code, _, err = run(capsys, "info", bad)
    assert code == 2 and err.startswith(f"dynbtf: error: {bad}: truncated") and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("command", [[], ["info"], ["convert"], ["show"], ["fit"], ["synth"]])
def test_help(capsys, command):
    code, out, _ = run(capsys, *command, "--help")
    assert code == 0 and "Usage" in out
    assert "<bool>" not in out and "{" not in out.split("Usage:")[1].splitlines()[0]  # flags; BTF, not {btf}
    if command in (["show"], ["fit"]):
        assert f"Usage: dynbtf {command[0]} [OPTIONS] BTF" in out
    if command == ["show"]:
        text = " ".join(out.replace("\u2502", " ").split())  # undo rich's wrapping and box borders
        assert "THETA,PHI in degrees" in text and ".exr" in text and "[default: 1.0]" in text


@pytest.mark.parametrize("argv,message", [(["demo", "--bogus"], "No such option: --bogus"),
                                          (["info"], "Missing argument"),
                                          (["fit", "x.dbtf", "--epochs", "many"], "Invalid value")])
def test_usage_errors_are_messages_not_tracebacks(capsys, argv, message):
    """A mistyped command line (typer bundles its own click) ends with click's usage message, exit status 2."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and "Usage: dynbtf" in err


def test_every_help_text_shows_its_bracketed_words(capsys):
    """Rich reads ``[word]`` in a help text as a markup tag and drops it (``[defaults]`` of a TOML manifest vanished
    from ``fit-many --help``): every command's and option's help escapes such brackets, and the rendered help of the
    one that has them shows them."""
    import click
    import typer.main

    from dynbtf.cli.main import app

    tag = re.compile(r"(?<!\\)\[/?[A-Za-z_@#][^\[\]\s]*\]")
    def commands(group, prefix=""):
        for name, command in group.commands.items():
            yield prefix + name, command
            if isinstance(command, click.Group):
                yield from commands(command, prefix + name + " ")

    checked = 0
    for name, command in commands(typer.main.get_command(app)):
        checked += 1
        texts = [command.help or ""] + [p.help or "" for p in command.params if isinstance(p, click.Parameter)
                                        and getattr(p, "help", None)]
        for text in texts:
            assert not tag.search(text), (name, tag.search(text).group(0), text)
    assert checked >= 15  # every command of the CLI
    code, out, _ = run(capsys, "fit-many", "--help")
    text = " ".join(out.replace("\u2502", " ").split())
    assert code == 0 and "TOML manifest: [defaults] and one [[source]] table per BTF" in text
