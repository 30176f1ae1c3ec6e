"""The Typer application object that every command module registers on.

Each command lives in its own module under :mod:`dynbtf.cli` and is a thin
wrapper over a library function (so every command is also a function call).
"""

from __future__ import annotations

import typer
import typer.core


def _conventional_help() -> None:
    """Help text as command-line users read it: on/off flags without a ``<bool>`` type column, and
    arguments in usage lines as ``BTF`` (required) or ``[BTF]`` (optional) rather than ``{btf}``.

    Typer 0.2x renders both its own way; these two small overrides of its help rendering (checked by
    tests/test_cli_help.py) are all that changes.
    """
    option_type = getattr(typer.core.TyperOption, "display_type_rich", None)
    if option_type is not None and not getattr(option_type, "_dynbtf", False):
        def display_type_rich(self, ctx):
            return None if getattr(self, "is_flag", False) else option_type(self, ctx)

        display_type_rich._dynbtf = True
        typer.core.TyperOption.display_type_rich = display_type_rich
    if hasattr(typer.core.TyperArgument, "_usage_display_name"):
        def _usage_display_name(self) -> str:
            name = (self.metavar or self.name or "").upper()
            name = name if self.required else f"[{name}]"
            return name + ("..." if self.nargs != 1 else "")

        typer.core.TyperArgument._usage_display_name = _usage_display_name


_conventional_help()

app = typer.Typer(
    name="dynbtf",
    help=(
        "dynbtf: turn a small measured BTF into an infinite, non-repeating material.\n\n"
        "Pipeline: represent (fit a Triple Plane) -> synthesize (dynamic by-example synthesis "
        "of the positional feature plane) -> recover (decode to RGB for rendering).\n\n"
        "Conventions: directions are given as (theta, phi) in degrees on the command line; "
        "uv is in units of one exemplar repeat; colours are linear RGB and exclude cos(theta_light)."
    ),
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


_STARTED: list[float] = []  # when the `dynbtf` command started (set by dynbtf.cli.main.main for the real command)


def process_age() -> float:
    """Seconds since this process started (Linux: from /proc; elsewhere 0)."""
    import os

    try:
        with open("/proc/self/stat", encoding="ascii") as f:
            start_ticks = float(f.read().rsplit(")", 1)[1].split()[19])
        with open("/proc/uptime", encoding="ascii") as f:
            uptime = float(f.read().split()[0])
        return max(0.0, uptime - start_ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError):
        return 0.0


def mark_command_start(include_process: bool) -> None:
    """Record the command's start (``time.perf_counter()``): the process's own start when it is the ``dynbtf``
    command (its interpreter and imports belong to the command's time), else now (a call from Python)."""
    import time

    _STARTED[:] = [time.perf_counter() - (process_age() if include_process else 0.0)]


def command_started() -> float:
    """``time.perf_counter()`` at the command's start (:func:`mark_command_start`; now when nothing marked it): what
    a time budget such as ``dynbtf fit --minutes`` counts from."""
    import time

    return _STARTED[0] if _STARTED else time.perf_counter()
