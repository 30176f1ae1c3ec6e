"""``dynbtf demo --quick`` end to end, resumed, and its report checked in headless Chromium."""

from __future__ import annotations

import json
import re

import pytest

from dynbtf.demo import STAGES, DemoConfig, run_demo
from dynbtf.errors import InputError
from browser import check_in_browser, find_chromium
from dynbtf.report.html import HtmlReport


@pytest.fixture(scope="module")
def quick_demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    logs: list[str] = []
    results = run_demo(DemoConfig(output=str(out), size=16, quick=True), progress=False, log=logs.append)
    return out, results, logs


def test_quick_demo_writes_every_stage_and_the_report(quick_demo):
    out, results, logs = quick_demo
    assert list(results) == list(STAGES)
    for stage in STAGES:
        record = json.loads((out / "stages" / f"{stage}.json").read_text())
        assert record["seconds"] >= 0
    assert (out / "model.dbtfm").is_file()
    assert results["evaluate"]["n_pairs"] > 0 and results["evaluate"]["mean"]["psnr"] > 5.0
    assert {row["method"] for row in results["synthesis"]["quality"]} == {"tile", "hist", "hex"}
    # tiling repeats exactly; histogram-preserving blending does not
    score = {row["method"]: row["repetition score"] for row in results["synthesis"]["quality"]}
    assert score["tile"] > 0.9 and score["hist"] < 0.5 * score["tile"]
    html = (out / "report.html").read_text()
    for src in re.findall(r"src='([^']+)'", html):
        assert (out / src).is_file(), src
    assert any(f"stage {len(STAGES)}/{len(STAGES)} report" in line for line in logs)
    # the real-time viewer is written next to the report and linked from it
    assert "viewer/index.html" in re.findall(r"href='([^']+)'", html)
    assert (out / "viewer" / "index.html").is_file() and (out / "viewer" / "manifest.js").is_file()
    manifest = json.loads((out / "viewer" / "manifest.json").read_text())
    assert manifest["methods"].keys() == {manifest["auto"]["method"], "hist", "tile"}
    # the structured material: auto picks struct, which keeps its structure (tiling's coherence is 0 by definition)
    st = results["structured"]
    assert st["material"] == "ceramic_tiles" and "auto -> struct" in st["choice"]
    coherence = {row["method"]: row["coherence p90"] for row in st["quality"]}
    assert coherence["tile"] < 1e-9 and coherence["auto (struct)"] < coherence["hist"]
    assert "A structured material: tile | hist | auto" in html
    # the two materials layered: the image shows the structured one exactly where the "shown" map says so, and the
    # layered viewer is written and linked
    lay = st["layered"]
    assert "a layered material" in html and all(lay[k] in html for k in ("mask", "image", "shown"))
    assert "layered-viewer/index.html" in re.findall(r"href='([^']+)'", html)
    assert (out / "layered-viewer" / "layered.js").is_file() and (out / "layered-viewer" / "layer1" / "manifest.js").is_file()
    from dynbtf.demo import _Context, _demo_layered

    layered = _demo_layered(_Context(DemoConfig(output=str(out), size=16, quick=True), out, False, print))
    assert [b.synthesizer.name for b in layered.layers] == lay["methods"] == ["hist", "struct"]
    # guided by a painted target: the dark-painted part of the image shows the darker content
    import imageio.v3 as iio
    import numpy as np

    from dynbtf.guided import example_target

    shown = iio.imread(out / lay["shown"]).astype(np.float64)[..., :3].mean(-1)
    assert 0.05 < (shown > 180).mean() < 0.95  # both materials show (sRGB levels 137 and 225)

    guided = results["synthesis"]["guided"]
    assert "Guided by a painted target" in html and guided["image"] in html and guided["target"] in html
    image = iio.imread(out / guided["image"]).astype(np.float64)[..., :3].mean(-1)
    side = image.shape[0]
    target = example_target()
    dark = target[np.arange(side) * target.shape[0] // side][:, np.arange(side) * target.shape[0] // side] < 0.5
    assert image[dark].mean() < image[~dark].mean()
    # words a reader understands: no raw keys, units, what finished, a command that works as typed
    import html as html_module
    import shlex
    import sys

    text = html_module.unescape(html)
    for raw in ("model_bytes", "compression_ratio", "f H pca", "training finished"):
        assert raw not in text, raw
    assert "finished (1 epochs)" in text and "principal components as RGB" in text
    assert "first call (compiles kernels)" in text and "size (px)" in text and " deg" in text
    reproduce = re.search(r"Reproduce \(reruns skip finished stages\): ([^<]+)", text).group(1)
    assert shlex.split(reproduce)[:4] == [sys.executable, "-m", "dynbtf", "demo"]


def test_rerun_resumes_by_skipping_finished_stages(quick_demo):
    out, first, _ = quick_demo
    logs: list[str] = []
    again = run_demo(DemoConfig(output=str(out), size=16, quick=True), progress=False, log=logs.append)
    skipped = [line for line in logs if "skipped" in line]
    assert len(skipped) == len(STAGES) - 1  # everything but the (cheap) report
    assert again["evaluate"]["mean"] == first["evaluate"]["mean"]


def test_demo_rejects_bad_options(tmp_path):
    with pytest.raises(InputError, match="--material"):
        run_demo(DemoConfig(output=str(tmp_path), material="velvet"), progress=False)
    with pytest.raises(InputError, match="--size"):
        run_demo(DemoConfig(output=str(tmp_path), size=2), progress=False)


@pytest.mark.browser
def test_report_as_a_person_sees_it_in_headless_chromium(quick_demo):
    if find_chromium() is None:
        pytest.skip("headless Chromium not installed (Debian: apt-get install chromium)")
    out, results, _ = quick_demo
    shot = out / "report-screenshot.png"
    seen = check_in_browser(out / "report.html", screenshot=shot, window=(1400, 2600))
    assert seen.title.startswith("dynbtf")
    assert len(seen.images) >= 15
    assert seen.broken_images == []
    assert all(i["naturalWidth"] > 0 and i["naturalHeight"] > 0 for i in seen.images)
    captions = " ".join(t["caption"] for t in seen.tables)
    for needed in ("Held-out metrics", "Model size", "Synthesis quality", "Structure measures", "Render settings",
                   "Wall time"):
        assert needed in captions
    assert all(t["rows"] >= 2 for t in seen.tables)  # header + at least one row
    import imageio.v3 as iio

    pixels = iio.imread(shot)
    assert pixels.shape[0] >= 2000 and pixels.std() > 10  # a real page, not a blank one


@pytest.mark.browser
def test_browser_check_notices_a_broken_image(tmp_path):
    if find_chromium() is None:
        pytest.skip("headless Chromium not installed (Debian: apt-get install chromium)")
    from dynbtf.io import save_image
    import numpy as np

    save_image(tmp_path / "ok.png", np.full((8, 8, 3), 0.5, dtype=np.float32))
    r = HtmlReport("probe")
    r.images([(tmp_path / "ok.png", "fine"), (tmp_path / "missing.png", "broken")])
    r.table([{"a": 1}], caption="t")
    seen = check_in_browser(r.write(tmp_path / "report.html"))
    assert seen.broken_images == ["missing.png"]
    assert [t["rows"] for t in seen.tables] == [2]


def test_demo_opens_a_users_btf_spec(tmp_path):
    results = run_demo(DemoConfig(output=str(tmp_path), btf="sim:stone?size=16", quick=True), progress=False,
                       log=lambda s: None, stages=("data",))
    d = results["data"]["describe"]
    assert (d["height"], d["width"]) == (16, 16) and "stone" in d["name"]
    assert all((tmp_path / x["path"]).is_file() for x in results["data"]["images"])


def test_demo_command_line_resumes_the_same_run(quick_demo, capsys):
    from dynbtf.cli.main import main

    out, _, _ = quick_demo
    assert main(["demo", "-o", str(out), "--size", "16", "--quick"]) == 0
    printed = capsys.readouterr().out
    assert printed.count("skipped") == len(STAGES) - 1 and "report.html" in printed
    assert main(["demo", "-o", str(out), "--material", "velvet"]) == 2
    assert "--material" in capsys.readouterr().err


def test_an_unfinished_fit_is_continued_by_the_next_run(tmp_path):
    """The time budget stopped the fit: the next run does not skip the stage, it continues the checkpoint."""
    logs: list[str] = []
    tiny = DemoConfig(output=str(tmp_path), size=16, quick=True, minutes=1e-5)  # stops after the first step
    first = run_demo(tiny, progress=False, log=logs.append, stages=("data", "fit"))
    assert first["fit"]["finished"] is False
    from dynbtf.report.demo_report import _training_state

    state = _training_state(first["fit"], tiny)
    assert state.startswith("not finished: the time budget stopped it after") and "run the same demo" in state
    logs.clear()
    second = run_demo(DemoConfig(output=str(tmp_path), size=16, quick=True), progress=False, log=logs.append,
                      stages=("data", "fit"))
    assert any("continuing the unfinished fit" in line for line in logs)
    assert not any("fit: done earlier" in line for line in logs)
    assert second["fit"]["finished"] is True
    logs.clear()
    run_demo(DemoConfig(output=str(tmp_path), size=16, quick=True), progress=False, log=logs.append,
             stages=("data", "fit"))
    assert any("fit: done earlier" in line for line in logs)  # finished now: skipped
