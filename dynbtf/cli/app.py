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
