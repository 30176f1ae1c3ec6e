"""The Typer application object that every command module registers on.

Each command lives in its own module under :mod:`dynbtf.cli` and is a thin
wrapper over a library function (so every command is also a function call).
"""

from __future__ import annotations

import typer

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
