"""Progress output: a live bar on a terminal, a few whole lines in a log."""

import io

from dynbtf.progress import LOG_INTERVAL_SECONDS, progress_bar


class Terminal(io.StringIO):
    def isatty(self):
        return True


def test_a_log_gets_whole_lines_not_carriage_returns():
    log = io.StringIO()
    for _ in progress_bar(range(5), desc="fit", unit="step", file=log, mininterval=0):
        pass
    text = log.getvalue()
    assert "\r" not in text and text.endswith("\n")
    lines = text.splitlines()
    assert 6 <= len(lines) <= 7 and lines[-1].startswith("fit: 100%") and "5/5" in lines[-1]  # + the close line
    assert all("step" in line for line in lines[1:])  # rate in steps


def test_a_log_line_keeps_every_postfix_field_however_long():
    """Progress lines in a log are not cut to a terminal width: the fit's last fields survive."""
    log = io.StringIO()
    bar = progress_bar(total=3, desc="fit triple-parallax on sim:woven_fabric?size=128", unit="step", file=log,
                       mininterval=0)
    for _ in range(3):
        bar.update(1)
        bar.set_postfix(loss="0.0123", samples_s="1.23e+07", heldout_psnr="31.42", chosen="triple-parallax")
    bar.close()
    last = log.getvalue().splitlines()[-1]
    assert len(last) > 100
    assert last.endswith("]") and "3/3" in last, last
    for field in ("loss=0.0123", "samples_s=1.23e+07", "heldout_psnr=31.42", "chosen=triple-parallax"):
        assert field in last, (field, last)


def test_a_bar_that_clears_itself_on_a_terminal_leaves_no_escape_codes_in_a_log():
    log = io.StringIO()
    outer = progress_bar(total=2, desc="fit", file=log, mininterval=0)
    for _ in progress_bar(range(3), desc="decoding BTF", file=log, leave=False, mininterval=0):
        pass
    outer.close()
    text = log.getvalue()
    assert "\x1b" not in text and "decoding BTF: 100%" in text


def test_a_fast_loop_in_a_log_writes_a_line_every_few_seconds_at_most():
    assert LOG_INTERVAL_SECONDS >= 2
    log = io.StringIO()
    for _ in progress_bar(range(20000), desc="decoding", file=log):
        pass
    assert len(log.getvalue().splitlines()) <= 3


def test_a_terminal_gets_the_live_bar():
    screen = Terminal()
    for _ in progress_bar(range(3), desc="fit", file=screen, mininterval=0):
        pass
    assert "\r" in screen.getvalue()


def test_messages_written_through_the_bar_are_lines(capsys):
    log = io.StringIO()
    bar = progress_bar(total=2, desc="fit", file=log)
    bar.write("time budget reached", file=log)
    bar.update(2)
    bar.close()
    assert "time budget reached\n" in log.getvalue()


def test_a_fit_logged_to_a_file_writes_a_few_lines_not_one_per_step(tmp_path):
    """A 390-step fit with stderr redirected to a file logs a handful of lines, not one per step."""
    import subprocess
    import sys

    log = tmp_path / "fit.log"
    with open(log, "w") as handle:
        done = subprocess.run([sys.executable, "-m", "dynbtf", "fit", "sim:leather?size=8", "-o",
                               str(tmp_path / "m.dbtfm"), "--epochs", "1", "--texel-groups", "4", "--repr", "triple"],
                              stdout=handle, stderr=subprocess.STDOUT, timeout=600)
    assert done.returncode == 0
    lines = log.read_text().splitlines()
    assert "\r" not in log.read_text() and "\x1b" not in log.read_text()
    assert 2 <= len(lines) <= 20, lines  # the recipe, progress every few seconds, the result
    assert any("390/390" in line for line in lines) and lines[-1].startswith("wrote ")
