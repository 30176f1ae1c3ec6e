"""Progress of long work: a bar on a terminal, a line every few seconds in a log.

Every long loop in dynbtf reports through :func:`progress_bar` (a configured ``tqdm``). On a
terminal it is tqdm's live bar with rate and ETA. When stderr is not a terminal (a log file, CI,
a pipe) the same bar is written as complete lines, at most one every :data:`LOG_INTERVAL_SECONDS`
plus the final state, each with every field the bar shows (never cut to a width), instead of a carriage-return update per step (a 3-epoch fit used to log
167 KB of them).

>>> import io
>>> log = io.StringIO()
>>> for _ in progress_bar(range(1000), desc="work", unit="step", file=log):
...     pass
>>> lines = log.getvalue().splitlines()
>>> len(lines) <= 2 and lines[-1].startswith("work: 100%")
True
"""

from __future__ import annotations

import io
import sys
from typing import Any, Iterable

__all__ = ["progress_bar", "LOG_INTERVAL_SECONDS"]

#: Seconds between progress lines when stderr is not a terminal.
LOG_INTERVAL_SECONDS = 5.0


class _LogLines(io.TextIOBase):
    """A text stream that turns tqdm's carriage-return refreshes into whole lines on ``target``."""

    def __init__(self, target) -> None:
        super().__init__()
        self.target, self._pending = target, ""

    def write(self, text: str) -> int:
        self._pending += text
        *done, self._pending = self._pending.replace("\r", "\n").split("\n")
        for line in done:
            if line.strip():
                self.target.write(line.rstrip() + "\n")
        return len(text)

    def flush(self) -> None:
        self.target.flush()


def _is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


def progress_bar(iterable: Iterable | None = None, *, file=None, **options: Any):
    """A ``tqdm`` progress bar (same arguments) that suits where it is written.

    ``file`` defaults to stderr. On a terminal: tqdm's live bar (dynamic width). Elsewhere: complete
    lines, one every :data:`LOG_INTERVAL_SECONDS` at most and one at the end, with the same rate, ETA and
    postfix fields, however long the line.
    """
    from tqdm.auto import tqdm

    target = sys.stderr if file is None else file
    if _is_terminal(target):
        options.setdefault("dynamic_ncols", True)
        return tqdm(iterable, file=target, **options)
    options.pop("dynamic_ncols", None)
    # no cursor movement in a log (ESC [A): a bar inside another's loop is not moved to a line of its own, and a
    # bar that would clear itself keeps its last line
    options["leave"], options["position"] = True, 0
    options.setdefault("mininterval", LOG_INTERVAL_SECONDS)
    # no ncols: tqdm then never trims a line, so every postfix field (loss, samples/s, held-out PSNR) is kept
    return tqdm(iterable, file=_LogLines(target), **options)
