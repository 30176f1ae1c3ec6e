"""The guided-synthesis options that ``dynbtf synth`` and ``dynbtf export`` share (one declaration each).

``dynbtf render`` declares its own: its sizes are in mesh uv units and struct's cells default to the method's own
choice. :func:`dynbtf.guided.guidance_options` checks the values for all three commands.
"""

from __future__ import annotations

from typing import Optional

import typer

__all__ = ["CLASSES", "TARGET_WRAP", "SOFTNESS", "CELLS", "BRIGHTNESS", "TINT", "ROTATION"]

CLASSES: int = typer.Option(2, "--classes", help="With --target: classes of the material's texels.")
TARGET_WRAP: str = typer.Option("repeat", "--target-wrap", help="The --target image repeats (repeat) or extends its "
                                "edges (clamp).")
SOFTNESS: float = typer.Option(0.0, "--softness", help="With --target: blend weight (0 to 1) of samples whose "
                               "content is not of the target's class (0: left out where another sample is).")
CELLS: Optional[int] = typer.Option(None, "--cells", help="struct: cells per exemplar repeat along u and v (must "
                                    "divide the exemplar's sides; default: 2 where a side allows it). With --target "
                                    "--method struct, about one cell per element.")
BRIGHTNESS: float = typer.Option(0.0, "--brightness", help="struct: per-element variation, the standard deviation "
                                 "of each element's log-brightness (each brick or tile its own factor, drawn from "
                                 "--seed; joints none), in [0, 1]; 0: off.")
TINT: float = typer.Option(0.0, "--tint", help="struct: per-element variation, the standard deviation of each "
                           "element's colour tint (its channels' log gains against each other), in [0, 1]; 0: off.")
SCALE_JITTER: float = typer.Option(0.0, "--scale-jitter", help="hist, hex, linear: magnify each lattice vertex's "
                                   "sample by a random factor between 1/(1 + J) and 1 + J (drawn from --seed), in "
                                   "[0, 1]; 0: off. Reads between texel centres: for models fitted with the "
                                   "sub-texel term (dynbtf fit's default).")
ROTATION: bool = typer.Option(False, "--rotation", help="hist, hex, linear: turn each lattice vertex's sample by "
                              "random quarter turns (drawn from --seed), the view and light turned with it; for "
                              "isotropic materials.")
