"""``--method auto``: the synthesis method chosen from how structured the exemplar is.

Structured exemplars (weaves, tiles, bricks: strong autocorrelation peaks away from zero lag,
:mod:`.structure`) are synthesized with lattice-aligned cell quilting (``struct``), which keeps
their elements intact; stochastic ones with histogram-preserving blending (``hist``), which
never repeats and keeps the histogram. A fitted model's appearance is measured rather than its feature plane when the caller gives it
(``guide``; :class:`dynbtf.infinite_btf.SynthesizedBTF` does). The choice and its evidence are one line,
:attr:`MethodChoice.line`, that every command prints.

Examples
--------
>>> import torch
>>> choice = choose_method(torch.rand(8, 8, 3).repeat(4, 4, 1))
>>> choice.method
'struct'
>>> choose_method(torch.rand(32, 32, 3)).method
'hist'
"""

from __future__ import annotations

from dataclasses import dataclass

from .structure import STRUCTURE_THRESHOLD, StructureAnalysis, analyze_structure

__all__ = ["MethodChoice", "choose_method", "AUTO"]

#: The name that asks for the automatic choice.
AUTO = "auto"


@dataclass(frozen=True)
class MethodChoice:
    """What ``auto`` chose (``method``), from which measurement (``analysis``)."""

    method: str
    analysis: StructureAnalysis

    @property
    def line(self) -> str:
        """``method auto -> struct: structure strength 0.93 (...) >= 0.50`` (one line)."""
        relation = ">=" if self.analysis.structured else "<"
        kind = "structured" if self.analysis.structured else "stochastic"
        return (f"method auto -> {self.method}: {kind} exemplar, {self.analysis.describe()} {relation} "
                f"{STRUCTURE_THRESHOLD:.2f}")


    @property
    def strength(self) -> float:
        """The measured structure strength."""
        return float(self.analysis.strength)

    def record(self) -> dict:
        """``{"method", "line", "strength"}`` (JSON): what a compiled material keeps of the choice."""
        return {"method": self.method, "line": self.line, "strength": self.strength}


@dataclass(frozen=True)
class RecordedChoice:
    """A :class:`MethodChoice` as stored (:meth:`MethodChoice.record`): its method, line and strength."""

    method: str
    line: str
    strength: float


def choose_method(exemplar, guide=None) -> MethodChoice:
    """``struct`` for a structured ``exemplar (H, W, C)``, else ``hist`` (see the module docstring).

    ``guide (H, W, G)``, when given, is measured instead: the exemplar's appearance (e.g. a fitted
    model's decoded colours; :class:`~dynbtf.synthesis.cell_quilting.CellQuilting`'s ``guide``).
    """
    analysis = analyze_structure(exemplar if guide is None else guide)
    return MethodChoice("struct" if analysis.structured else "hist", analysis)
