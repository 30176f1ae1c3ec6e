"""Untrusted input through the command line: manifests (``fit-many``), output paths, sizes and scales,
Mitsuba's LLVM. Each mistake is one clear line (``dynbtf: error: ...``, exit status 2), never a
traceback, a hang, a process killed for memory or a file written outside the output directory.

Part of the untrusted-input issue; the manifest fuzz at the end runs a few hundred seeded mutations
through ``dynbtf fit-many --check`` (no Ray needed).
"""

from __future__ import annotations

import glob
import os
import random
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dynbtf.cli.main import main


def _tree(root: Path) -> set[str]:
    """Every path under ``root`` (files and directories), relative."""
    return {str(p.relative_to(root)) for p in root.rglob("*")}


def _one_error(capsys, *needles: str) -> str:
    """Exactly one non-empty line on stderr, ``dynbtf: error: ...``, containing every needle; no traceback."""
    captured = capsys.readouterr()
    lines = [line for line in captured.err.splitlines() if line.strip()]
    assert "Traceback" not in captured.err and "Traceback" not in captured.out, captured.err
    assert len(lines) == 1 and lines[0].startswith("dynbtf: error: "), captured.err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def _manifest(tmp_path: Path, text: str | bytes, name: str = "m.toml") -> Path:
    path = tmp_path / name
    path.write_bytes(text if isinstance(text, bytes) else text.encode("utf-8"))
    return path


# ------------------------------------------------------------------------------------------- path escapes
@pytest.mark.parametrize("name", ["../../x", "/tmp/dynbtf-escape", "a/b", "..", ".", ".hidden", "-x", "a\\\\b", ""])
def test_a_source_name_that_would_leave_the_output_directory_is_refused(tmp_path, capsys, name):
    root = tmp_path / "root"
    (root / "in").mkdir(parents=True)
    manifest = _manifest(root / "in", f'[[source]]\nbtf = "sim:leather?size=8"\nname = "{name}"\n')
    before = _tree(tmp_path)
    assert main(["fit-many", str(manifest), "-o", str(root / "in" / "out")]) == 2
    line = _one_error(capsys, "m.toml:3: [[source]] #1 name", "so that its model is written inside the output directory")
    assert "is a path" in line or "starts with" in line or "empty" in line or "contains" in line
    assert _tree(tmp_path) == before  # nothing written, inside or outside
    assert not Path("/tmp/dynbtf-escape.dbtfm").exists()


def test_every_bad_source_is_reported_together_and_nothing_runs(tmp_path, capsys, monkeypatch):
    import dynbtf.fit_many as fm

    monkeypatch.setattr(fm, "optional_module", lambda *a: pytest.fail("Ray was reached"))
    manifest = _manifest(tmp_path, '[[source]]\nbtf = "sim:leather?size=8"\nname = "good"\n\n'
                                   '[[source]]\nbtf = "sim:stone?size=8"\nname = "../up"\n\n'
                                   '[[source]]\nbtf = "sim:stone?size=8"\nname = "/abs/path"\n\n'
                                   '[[source]]\nbtf = "sim:stone?size=8"\nepochs = -3\n\n'
                                   '[[source]]\nbtf = "sim:stone?size=8"\nname = "' + "n" * 300 + '"\n')
    assert main(["fit-many", str(manifest), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert err.startswith("dynbtf: error: ") and "4 problems, nothing was run" in err
    for needle in ("m.toml:7: [[source]] #2 name '../up' is a path", "m.toml:11: [[source]] #3 name '/abs/path' is a path",
                   "m.toml:15:", "'epochs'", "m.toml:19: [[source]] #5 name", "has 300 characters; at most 100"):
        assert needle in err, (needle, err)
    assert "#1" not in err  # the good one is not a problem
    assert not (tmp_path / "out").exists()


def test_a_manifest_of_many_bad_sources_lists_fifty_and_counts_the_rest(tmp_path, capsys):
    manifest = _manifest(tmp_path, "".join(f'[[source]]\nbtf = "sim:leather?size=8"\nname = "../n{i}"\n'
                                           for i in range(3000)))
    assert main(["fit-many", str(manifest), "-o", str(tmp_path / "out"), "--check"]) == 2
    err = capsys.readouterr().err
    assert "3000 problems, nothing was run" in err and err.rstrip().endswith("... and 2950 more")
    assert len(err.splitlines()) == 52


def test_default_names_from_odd_files_stay_inside_the_output_directory(tmp_path):
    from dynbtf.fit_many import read_manifest

    # (missing files: left to their tasks; a sim: spec is opened up front, so an unknown material is refused there)
    manifest = _manifest(tmp_path, '[[source]]\nbtf = "../../..btf"\n[[source]]\nbtf = "..x.zip"\n'
                                   '[[source]]\nbtf = "/x/' + "y" * 300 + '.btf"\n[[source]]\nbtf = "d/-a b.zip"\n')
    out = tmp_path / "out"
    tasks = read_manifest(manifest, out)
    for task in tasks:
        assert task.model_path.resolve().parent == out.resolve(), task.name
        assert not task.name.startswith((".", "-")) and len(task.name) <= 100
    assert [t.name for t in tasks][-1] == "a_b"


# ------------------------------------------------------------------------------------------- encodings
@pytest.mark.parametrize("data, needles", [
    (b'[[source]]\nbtf = "sim:leather?size=8"\n# caf\xe9\n', ("m.toml:3: byte 0xe9 (column 6) is not UTF-8",)),
    (b'\xff\xfe[\x00[\x00', ("m.toml:1: byte 0xff", "UTF-8")),
    (b'[[source]]\nbtf = "sim:leather?size=8"\nname = "a\\u0000b"\n', ("m.toml:3: [[source]] #1 name 'a\\x00b' contains '\\x00'",)),
    (b'[[source]]\nbtf = "sim:leather?size=8"\nname = "' + b"x" * 300 + b'"\n', ("has 300 characters; at most 100",)),
    (b'[[source]]\nbtf = "sim:leather?size=8"\nepochs = ' + b"[" * 100000 + b"]" * 100000 + b"\n",
     ("nested too deeply",)),
    (b'[[source]]\nbtf = "sim:leather?size=8"\nepochs = {a = ' * 3000 + b'1' + b'}' * 3000 + b"\n",
     ("m.toml",)),
    (b'[[source]]\nbtf = "a\\u0000.btf"\n', ("key 'btf'", "without NUL")),
    (b'[[source]]\nbtf = "sim:leather?size=8"\nminutes = nan\n', ("'minutes' = nan: expected a finite number",)),
    (b'[[source]]\nbtf = "sim:leather?size=8"\nseed = 99999999999999999999\n', ("out of range",)),
    (b'[[source]]\nbtf = "sim:leather?size=8"\nepochs = [' + b"1," * 100000 + b"1]\n", ("expected int",)),
    (b'source = 3\n', ("'source' must be an array of tables",)),
    (b'source = [1, 2]\n', ("'source' must be an array of tables",)),
])
def test_manifest_bytes_that_are_not_a_valid_manifest_are_one_clear_line(tmp_path, capsys, data, needles):
    manifest = _manifest(tmp_path, data)
    started = time.perf_counter()
    assert main(["fit-many", str(manifest), "-o", str(tmp_path / "out"), "--check"]) == 2
    line = _one_error(capsys, *needles)
    assert len(line) < 2000  # a value of megabytes is not echoed
    assert time.perf_counter() - started < 20
    assert not (tmp_path / "out").exists()


def test_a_utf8_manifest_with_a_bom_and_unicode_comments_is_accepted(tmp_path, capsys):
    manifest = _manifest(tmp_path, '\ufeff# Café, 東京\n[[source]]\nbtf = "sim:leather?size=8"\nname = "leather"\n')
    assert main(["fit-many", str(manifest), "-o", str(tmp_path / "out"), "--check"]) == 0
    out = capsys.readouterr().out
    assert "leather: sim:leather?size=8 ->" in out and "1 source(s) checked; nothing was run" in out
    assert not (tmp_path / "out").exists()


def test_an_oversized_manifest_is_refused_before_it_is_read(tmp_path, capsys, monkeypatch):
    import dynbtf.fit_many as fm

    monkeypatch.setattr(fm, "MAX_MANIFEST_BYTES", 1000)
    manifest = _manifest(tmp_path, '[[source]]\nbtf = "sim:leather?size=8"\n' + "# padding\n" * 200)
    assert main(["fit-many", str(manifest), "-o", str(tmp_path / "out"), "--check"]) == 2
    _one_error(capsys, "a manifest is at most 1000 bytes")


# ------------------------------------------------------------------------------------------- resources
@pytest.fixture
def good_manifest(tmp_path):
    return _manifest(tmp_path, '[[source]]\nbtf = "sim:leather?size=8"\n')


@pytest.mark.parametrize("args, needles", [
    (["--cpus", "-4"], ("--cpus: expected 1..65536 CPUs", "got -4")),
    (["--cpus", "0"], ("--cpus: expected 1..65536",)),
    (["--cpus-per-task", "0"], ("--cpus-per-task: expected 1..4096",)),
    (["--cpus", "1", "--cpus-per-task", "2"],
     ("--cpus-per-task 2: no task could ever be scheduled", "has 1 CPU(s)", "expected --cpus-per-task 1 or less")),
    (["--cpus-per-task", "100000"], ("--cpus-per-task: expected 1..4096",)),
    (["--cpus-per-task", "4096"], ("no task could ever be scheduled",)),
    (["--max-retries", "-1"], ("--max-retries: expected 0..100",)),
    (["--address", "foo"], ("--address 'foo': expected 'auto', HOST:PORT",)),
    (["--address", "ray://"], ("--address 'ray://': expected",)),
    (["--address", "http://h:1"], ("--address 'http://h:1': expected",)),
    (["--address", "host:99999"], ("--address 'host:99999': expected",)),
    (["--address", ":::"], ("expected 'auto', HOST:PORT",)),
])
def test_infeasible_or_malformed_resources_are_refused_before_ray_starts(tmp_path, capsys, good_manifest, monkeypatch,
                                                                          args, needles):
    import dynbtf.fit_many as fm

    monkeypatch.setattr(fm, "optional_module", lambda *a: pytest.fail("Ray was reached"))
    before = _tree(tmp_path)
    for extra in ([], ["--check"]):
        assert main(["fit-many", str(good_manifest), "-o", str(tmp_path / "out"), *args, *extra]) == 2
        _one_error(capsys, *needles)
    assert _tree(tmp_path) == before


def test_an_unreachable_address_is_one_line_within_seconds(tmp_path, capsys, good_manifest):
    pytest.importorskip("ray")
    with __import__("socket").socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    started = time.perf_counter()
    assert main(["fit-many", str(good_manifest), "-o", str(tmp_path / "out"), "--address", f"127.0.0.1:{port}"]) == 2
    _one_error(capsys, f"--address '127.0.0.1:{port}': cannot reach 127.0.0.1:{port}", "ray start --head")
    assert time.perf_counter() - started < 30
    assert not (tmp_path / "out").exists()


def test_an_open_port_that_is_not_ray_times_out_with_one_line(tmp_path, capsys, good_manifest, monkeypatch):
    pytest.importorskip("ray")
    import socket

    import dynbtf.fit_many as fm

    monkeypatch.setattr(fm, "CONNECT_TIMEOUT", 8.0)
    with socket.socket() as server:  # accepts connections, says nothing: not a Ray head
        server.bind(("127.0.0.1", 0))
        server.listen(8)
        port = server.getsockname()[1]
        started = time.perf_counter()
        assert main(["fit-many", str(good_manifest), "-o", str(tmp_path / "out"), "--address",
                     f"127.0.0.1:{port}"]) == 2
        elapsed = time.perf_counter() - started
    line = _one_error(capsys, f"--address '127.0.0.1:{port}'")
    assert "no Ray cluster answered within 8 s" in line or "cannot connect to a Ray cluster" in line
    assert elapsed < 40


# ------------------------------------------------------------------------------------------- outputs
def test_outputs_that_cannot_be_created_are_refused_up_front(tmp_path, capsys, small_model, good_manifest):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    before = _tree(tmp_path)
    cases = [
        (["synth", str(small_model), "-o", str(a_file / "x.png")], "is a file, not a directory"),
        (["synth", str(small_model), "--report", "--report-json", str(a_file / "q.json")], "--report-json"),
        (["render", str(small_model), "-o", str(a_file / "x.png")], "is a file, not a directory"),
        (["export", str(small_model), "-o", str(a_file / "web")], "is a file, not a directory"),
        (["export", str(small_model), "-o", str(a_file)], "exists and is not a directory"),
        (["fit-many", str(good_manifest), "-o", str(a_file)], "exists and is not a directory"),
        (["fit-many", str(good_manifest), "-o", str(a_file / "out")], "is a file, not a directory"),
    ]
    for args, needle in cases:
        assert main(args) == 2, args
        _one_error(capsys, "-o" if "--report-json" not in args else "--report-json", needle)
    assert _tree(tmp_path) == before


def test_fit_refuses_an_unwritable_output_before_opening_the_btf(tmp_path, capsys, monkeypatch):
    import dynbtf.training as training

    def refuse(*args, **kwargs):
        raise AssertionError("the fitter was looked up before -o/--output was checked")

    monkeypatch.setattr(training, "get_fitter", refuse)
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    before = _tree(tmp_path)
    missing = str(tmp_path / "nothere.dbtf")  # the output is checked first: this BTF is never opened
    for output, needle in ((a_file / "m.dbtfm", "is a file, not a directory"),
                           (tmp_path, "is a directory; expected a file name in it")):
        assert main(["fit", missing, "-o", str(output), "--epochs", "1"]) == 2
        _one_error(capsys, "-o/--output", needle)
    assert _tree(tmp_path) == before


def test_check_writable_names_the_problem(tmp_path):
    from dynbtf.errors import InputError
    from dynbtf.io import check_writable

    assert check_writable(tmp_path / "new" / "deeper" / "x.dbtfm", "-o") == tmp_path / "new" / "deeper" / "x.dbtfm"
    assert not (tmp_path / "new").exists()  # nothing created
    with pytest.raises(InputError, match=r"is a directory; expected a file name in it"):
        check_writable(tmp_path, "-o")  # `dynbtf fit ... -o .`
    (tmp_path / "f").write_text("x")
    with pytest.raises(InputError, match=r"f/x.dbtfm: cannot be created: .*f is a file, not a directory"):
        check_writable(tmp_path / "f" / "x.dbtfm", "-o")
    with pytest.raises(InputError, match="exists and is not a directory"):
        check_writable(tmp_path / "f", "-o", directory=True)
    with pytest.raises(InputError, match="no space left on device"):
        check_writable(tmp_path / "x.png", "-o", needed_bytes=2**62)


def _unshare_available() -> bool:
    if not shutil.which("unshare"):
        return False
    probe = subprocess.run(["unshare", "-rm", "sh", "-c", "mount -t tmpfs -o size=64k tmpfs /mnt"],
                           capture_output=True, timeout=30)
    return probe.returncode == 0


@pytest.mark.skipif(sys.platform != "linux", reason="a tmpfs in a private mount namespace (Linux)")
def test_a_full_disk_and_a_read_only_file_system_are_one_line_with_no_stray_file(tmp_path, small_model):
    if not _unshare_available():
        pytest.skip("no unprivileged mount namespaces here (unshare -rm)")
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    run = f"{sys.executable} -m dynbtf"
    script = f"""
set -u
mount -t tmpfs -o size=64k tmpfs {mnt}
{run} synth {small_model} -o {mnt}/s.png --resolution 512 --method hist > /dev/null 2> {tmp_path}/png.err; echo $? > {tmp_path}/png.rc
{run} synth {small_model} -o {mnt}/s.exr --resolution 512 --method hist > /dev/null 2> {tmp_path}/exr.err; echo $? > {tmp_path}/exr.rc
{run} export {small_model} -o {mnt}/web --method hist --method tile > /dev/null 2> {tmp_path}/web.err; echo $? > {tmp_path}/web.rc
find {mnt} -name '*.tmp*' > {tmp_path}/stray.txt
ls -A {mnt} > {tmp_path}/top.txt
mount -o remount,ro {mnt}
{run} synth {small_model} -o {mnt}/r.png --resolution 8 > /dev/null 2> {tmp_path}/ro.err; echo $? > {tmp_path}/ro.rc
{run} export {small_model} -o {mnt}/web2 > /dev/null 2> {tmp_path}/ro2.err; echo $? > {tmp_path}/ro2.rc
"""
    done = subprocess.run(["unshare", "-rm", "sh", "-c", script], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr

    def outcome(name):
        err = (tmp_path / f"{name}.err").read_text()
        lines = [line for line in err.splitlines() if line.strip()]
        return int((tmp_path / f"{name}.rc").read_text()), lines, err

    for name, path in (("png", f"{mnt}/s.png"), ("exr", f"{mnt}/s.exr"), ("web", f"{mnt}/web/")):
        status, lines, err = outcome(name)
        assert status == 2 and "Traceback" not in err and "Exception ignored" not in err, err
        assert len(lines) == 1 and lines[0].startswith(f"dynbtf: error: {path}"), err
        assert lines[0].endswith(": no space left on device"), err
    assert (tmp_path / "stray.txt").read_text() == ""  # no temporary file left behind
    assert "s.png" not in (tmp_path / "top.txt").read_text().split()
    for name in ("ro", "ro2"):
        status, lines, err = outcome(name)
        assert status == 2 and len(lines) == 1 and "Traceback" not in err, err
        assert lines[0].startswith("dynbtf: error: -o/--output ") and lines[0].endswith("read-only file system"), err
    assert list(mnt.iterdir()) == []  # the mount is gone with its namespace: nothing was written here


# ------------------------------------------------------------------------------------------- sizes and scales
def _no_model_load(monkeypatch):
    """Fail if a command loads the model: the limits below must be checked before any work."""
    import dynbtf.representations.model_file as model_file

    def refuse(*args, **kwargs):
        raise AssertionError("the model was loaded before the arguments were checked")

    monkeypatch.setattr(model_file, "load_model", refuse)
    monkeypatch.setattr(model_file, "read_model_metadata", refuse)


@pytest.mark.parametrize("args, needles", [
    (["--resolution", "100000"], ("--resolution 100000 (1e+10 pixels", "needs about 1 TB of memory",
                                  "above the limit of 4.1 GB (--memory-mb 4096)")),
    (["--resolution", "20000"], ("--resolution 20000", "needs about 40 GB of memory", "expected a smaller --resolution")),
    (["--spp", "3000", "--resolution", "1"], ("--spp: expected 1..64 samples per pixel axis, got 3000",)),
    (["--resolution", "4096", "--spp", "32"], ("is 1.72e+10 queries", "above the limit of 4.29e+09")),
    (["--scale", "1e300"], ("--scale: 1e+300 exemplar repeats", "2**52", "expected a positive scale below")),
    (["--scale", "nan"], ("--scale: expected a positive, finite number",)),
    (["--scale", "inf"], ("--scale: expected a positive, finite number",)),
    (["--scale", "-3"], ("--scale: expected a positive, finite number",)),
    (["--scale", "1e15", "--center", "10,10"], ("--center", "2**52")),
    (["--memory-mb", "nan"], ("--memory-mb: expected a positive number of MB",)),
])
def test_synth_refuses_extreme_sizes_and_scales_up_front(tmp_path, capsys, small_model, monkeypatch, args, needles):
    _no_model_load(monkeypatch)
    out = tmp_path / "s.png"
    memory = [] if "--memory-mb" in args else ["--memory-mb", "4096"]
    assert main(["synth", str(small_model), "-o", str(out), *memory, *args]) == 2
    _one_error(capsys, *needles)
    assert _tree(tmp_path) == set()


@pytest.mark.parametrize("args, needles", [
    (["--scale", "1e300"], ("--scale: 1e+300 exemplar repeats", "16777216 (2**24)", "Mitsuba's float32 uv")),
    (["--scale", "1e17"], ("--scale: 1e+17 exemplar repeats", "expected a positive scale below 16777216")),
    (["--scale", "nan"], ("--scale: expected a positive, finite number",)),
    (["--size", "100000"], ("--size 100000 (1e+10 pixels, 4 samples per pass) needs about 21 TB of memory",
                            "(--memory-mb 4096)")),
    (["--size", "3000"], ("--size 3000", "needs about 18.9 GB")),
    (["--spp", "100000"], ("--spp: expected 1..65536 samples per pixel",)),
    (["--spp", "5000", "--size", "1000"], ("is 5e+09 samples, above the limit of 4.29e+09",)),
])
def test_render_refuses_extreme_sizes_and_scales_before_mitsuba(tmp_path, capsys, small_model, monkeypatch, args,
                                                                 needles):
    import dynbtf.render.mitsuba.scene_render as scene_render

    _no_model_load(monkeypatch)
    monkeypatch.setattr(scene_render, "render_scene", lambda *a, **k: pytest.fail("render_scene was reached"))
    out = tmp_path / "r.png"
    assert main(["render", str(small_model), "-o", str(out), "--memory-mb", "4096", *args]) == 2
    _one_error(capsys, *needles)
    assert _tree(tmp_path) == set()


def test_render_scene_checks_its_limits_before_loading_anything(tmp_path):
    from dynbtf.errors import InputError
    from dynbtf.render.mitsuba.scene_render import render_scene

    missing = tmp_path / "missing.dbtfm"  # a file error would mean the limits came second
    for kwargs, match in (({"scale": 1e300}, "2\\*\\*24"), ({"scale": float("nan")}, "finite"),
                          ({"resolution": (100000, 100000), "memory_mb": 4096}, "TB of memory"),
                          ({"spp": 10**6}, "1..65536")):
        with pytest.raises(InputError, match=match):
            render_scene(missing, **kwargs)


@pytest.mark.parametrize("scale, needle", [
    ("nan", "got nan"), ("inf", "got inf"), ("0", "got 0.0"), ("-3", "got -3.0"),
    ("1e300", "exceed the 4096 that the shader's float32 local uv"), ("5000", "expected a positive scale below 4096"),
])
def test_export_refuses_a_scale_the_shader_cannot_hold(tmp_path, capsys, small_model, monkeypatch, scale, needle):
    _no_model_load(monkeypatch)
    assert main(["export", str(small_model), "-o", str(tmp_path / "web"), "--scale", scale]) == 2
    _one_error(capsys, "--scale", needle)
    assert not (tmp_path / "web").exists()


def test_check_scale_is_the_library_rule():
    from dynbtf.errors import InputError
    from dynbtf.limits import FLOAT32_MAX_REPEATS, MAX_REPEATS, check_scale
    from dynbtf.synthesis.lattice import MAX_REPEATS as LATTICE_MAX

    assert MAX_REPEATS == LATTICE_MAX
    assert check_scale(MAX_REPEATS / 2) == MAX_REPEATS / 2
    with pytest.raises(InputError):
        check_scale(MAX_REPEATS)
    assert check_scale(FLOAT32_MAX_REPEATS - 1, float32=True) == FLOAT32_MAX_REPEATS - 1
    with pytest.raises(InputError):
        check_scale(FLOAT32_MAX_REPEATS, float32=True)
    with pytest.raises(InputError, match="uv range \\(\\|uv\\| up to 1e\\+06\\)"):
        check_scale(1e10, extent=1e6)
    for bad in (float("nan"), float("inf"), -1.0, 0.0, "x", None, 10**400):
        with pytest.raises(InputError):
            check_scale(bad)


# ------------------------------------------------------------------------------------------- LLVM
def _render_with_llvm(small_model, tmp_path, library: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "DRJIT_LIBLLVM_PATH": library}
    return subprocess.run([sys.executable, "-m", "dynbtf", "render", str(small_model), "-o", str(tmp_path / "r.png"),
                           "--size", "8", "--spp", "1"], capture_output=True, text=True, env=env, timeout=300)


def test_render_with_a_missing_llvm_library_is_one_clear_line(tmp_path, small_model):
    pytest.importorskip("drjit")
    done = _render_with_llvm(small_model, tmp_path, str(tmp_path / "no" / "libLLVM.so"))
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr and "LLVM ERROR" not in done.stderr
    line = [x for x in done.stderr.splitlines() if x.startswith("dynbtf: error: ")]
    assert len(line) == 1 and "could not load the LLVM library DRJIT_LIBLLVM_PATH=" in line[0], done.stderr
    assert "install LLVM 16 or newer" in line[0] and "DRJIT_LIBLLVM_PATH" in line[0]
    assert not (tmp_path / "r.png").exists()


OLD_LLVMS = sorted(p for p in glob.glob("/usr/lib/*/libLLVM-1[45].so") + glob.glob("/usr/lib/*/libLLVM-1[45].so.1")
                   if os.path.exists(p))


@pytest.mark.skipif(not OLD_LLVMS, reason="no LLVM 14 or 15 library on this machine")
@pytest.mark.parametrize("library", OLD_LLVMS[:2])
def test_render_with_an_old_llvm_is_refused_before_it_aborts(tmp_path, small_model, library):
    pytest.importorskip("drjit")
    done = _render_with_llvm(small_model, tmp_path, library)
    assert done.returncode == 2, done.stderr  # LLVM 15 would abort the process (status -6/134) while compiling
    assert "LLVM ERROR" not in done.stderr and "Traceback" not in done.stderr
    line = [x for x in done.stderr.splitlines() if x.startswith("dynbtf: error: ")]
    major = "14" if "14" in os.path.basename(library) else "15"
    assert len(line) == 1 and f"LLVM {major}" in line[0] and "needs LLVM 16 or newer" in line[0], done.stderr
    system = subprocess.run([sys.executable, "-m", "dynbtf", "system"], capture_output=True, text=True, timeout=120,
                            env={**os.environ, "DRJIT_LIBLLVM_PATH": library})
    assert system.returncode == 0
    llvm = [x for x in system.stdout.splitlines() if x.startswith("LLVM (Dr.Jit)")]
    assert len(llvm) == 1 and "problem:" in llvm[0] and f"LLVM {major}" in llvm[0], system.stdout


def test_system_prints_what_was_found(capsys):
    assert main(["system"]) == 0
    out = capsys.readouterr().out
    for name in ("dynbtf", "python", "torch", "numba", "mitsuba", "drjit", "chromium"):
        assert any(line.startswith(name) for line in out.splitlines()), (name, out)
    if "drjit" in sys.modules and "not installed" not in out:
        assert "LLVM (Dr.Jit)" in out


# ------------------------------------------------------------------------------------------- the fuzz
NASTY_NAMES = ["../x", "../../x", "/etc/x", "/tmp/dynbtf-fuzz-escape", "a/b", "a\\b", "..", ".", "", " ", "-x", ".x",
               "x" * 101, "x" * 300, "a\u0000b", "a\nb", "ñ", "東京", "a b", "C:\\x", "x/../y", "~", "$HOME", "*",
               "good", "good.v2", "_under", "x" * 100]
VALUES = ["nan", "inf", "-inf", "1e308", "-0", "0", "-1", "18446744073709551616", "9223372036854775807", "1.5",
          '"many"', "[]", "[1, 2]", "{}", "{a = 1}", "true", "1979-05-27", "0x10", "1_000", '"\\u0000"',
          '"' + "s" * 5000 + '"', "[" * 50 + "]" * 50]
KEYS = ["epochs", "minutes", "seed", "repr", "recipe", "lr_scale", "memory_mb", "texel_groups", "precision",
        "device", "name", "btf", "unknown_key", "held_out_fraction"]
BASE = ('[defaults]\nepochs = 2\ntexel_groups = 4\n\n[[source]]\nbtf = "sim:leather?size=8"\nname = "leather"\n\n'
        '[[source]]\nbtf = "stone.dbtf"\nepochs = 3\n')


def _mutate(rng: random.Random) -> bytes:
    """One seeded mutation of BASE: bytes, names, nesting, types, numbers (or several)."""
    text = BASE
    for _ in range(rng.choice((1, 1, 2, 3))):
        kind = rng.choice(("bytes", "name", "nesting", "type", "number", "table", "source"))
        if kind == "name":
            text = text.replace('name = "leather"', f'name = "{rng.choice(NASTY_NAMES)}"'
                                .replace("\u0000", "\\u0000").replace("\n", "\\n").replace("\\b", "\\\\b")
                                .replace("\\x", "\\\\x"))
        elif kind == "nesting":
            depth = rng.choice((2, 50, 500, 5000, 100000))
            text += f"{rng.choice(KEYS)} = {'[' * depth}{rng.choice(('', '1', 'nan'))}{']' * depth}\n"
        elif kind in ("type", "number"):
            value = rng.choice(VALUES if kind == "type" else VALUES[:10])
            text += f"{rng.choice(KEYS)} = {value}\n"
        elif kind == "table":
            text = rng.choice(("[defaults]\nepochs = 1\n", "[[defaults]]\n", "[source]\nbtf = 1\n", "[x]\n",
                               "source = 3\n", "[[source.x]]\n")) + text
        elif kind == "source":
            text += f'\n[[source]]\nbtf = "{rng.choice(("", "sim:", "x" * 5000, "../../etc/passwd", "/abs.btf"))}"\n'
        data = text.encode("utf-8", "surrogateescape")
        if kind == "bytes":
            data = bytearray(data)
            for _ in range(rng.randint(1, 4)):
                op, at = rng.choice(("flip", "insert", "delete")), rng.randrange(len(data))
                if op == "flip":
                    data[at] = rng.randrange(256)
                elif op == "insert":
                    data[at:at] = bytes([rng.choice((0, 0xFF, 0xE9, 0xC3, ord("["), ord('"'), ord("\n"),
                                                     rng.randrange(256)))])
                else:
                    del data[at]
            text = bytes(data).decode("utf-8", "surrogateescape")
    return text.encode("utf-8", "surrogateescape")


def test_seeded_manifest_fuzz_through_the_cli_never_tracebacks_or_escapes(tmp_path, capsys):
    """300 seeded mutations of a manifest through `dynbtf fit-many --check`: exit 0 or 2, one error line or
    the task list, no traceback, nothing written anywhere, every accepted model path inside -o; bounded time
    and memory."""
    from dynbtf.fit_many import read_manifest

    (tmp_path / "stone.dbtf").write_bytes(b"")  # the manifest's relative BTF (never opened by --check)
    rng = random.Random(20261125)
    counts = {"cases": 0, "accepted": 0, "clean errors": 0, "tracebacks": 0, "escapes": 0}
    peak_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    started = time.perf_counter()
    slowest = 0.0
    for case in range(300):
        work = tmp_path / f"case{case}"
        work.mkdir()
        data = _mutate(rng)
        manifest = work / "m.toml"
        manifest.write_bytes(data)
        out = work / "out"
        t0 = time.perf_counter()
        status = main(["fit-many", str(manifest), "-o", str(out), "--check"])
        slowest = max(slowest, time.perf_counter() - t0)
        captured = capsys.readouterr()
        counts["cases"] += 1
        context = f"case {case}: {data[:300]!r}\n{captured.err[-2000:]}"
        assert status in (0, 2), context
        if "Traceback" in captured.err + captured.out:
            counts["tracebacks"] += 1
        assert "Traceback" not in captured.err + captured.out, context
        if status == 2:
            counts["clean errors"] += 1
            assert captured.err.startswith("dynbtf: error: ") and captured.out == "", context
            assert len(captured.err) < 20000, context
        else:
            counts["accepted"] += 1
            assert "nothing was run (--check)" in captured.out, context
            for task in read_manifest(manifest, out):
                if task.model_path.resolve().parent != out.resolve():
                    counts["escapes"] += 1
                assert task.model_path.resolve().parent == out.resolve(), context
        assert sorted(p.name for p in work.iterdir()) == ["m.toml"], context  # nothing written, not even -o
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith("case")) == ["stone.dbtf"]
    elapsed = time.perf_counter() - started
    grown_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - peak_before) / 1024
    print(f"\nmanifest fuzz: {counts}, {elapsed:.1f} s (slowest case {slowest:.2f} s), peak RSS +{grown_mb:.0f} MB")
    assert counts["accepted"] >= 10 and counts["clean errors"] >= 150  # the fuzz reaches both sides
    assert elapsed < 60 and slowest < 5 and grown_mb < 500
