"""Rules for stored tables, checked before any kernel reads them.

A compiled material (:mod:`dynbtf.material`) carries a synthesis method's off-line tables
and the folded decoders. A file may come from anyone, and its checksum proves only that it was not
damaged on the way, not that its tables make sense: a NaN histogram bound or an offset index past the
cut tables sends a compiled kernel outside its arrays. So whoever stores tables declares them
(:meth:`dynbtf.synthesis.base.Synthesizer.stored_tables`, :meth:`dynbtf.decoder.folded.FoldedDecoder.stored_tables`)
as :class:`Table` rules -- name, dtype, shape, value bounds, monotone rows -- and :func:`check_tables`
holds the stored arrays to them: the exact set of names, then each array (:class:`TableError` names
the table and what was expected).

>>> import torch
>>> rules = [Table("lut", torch.float32, (2, None), low=-4, high=4, monotone=True)]
>>> check_tables({"lut": torch.tensor([[0.0, 1.0], [2.0, 3.0]])}, rules)
>>> check_tables({"lut": torch.tensor([[1.0, 0.0], [2.0, 3.0]])}, rules)
Traceback (most recent call last):
...
dynbtf.tables.TableError: table 'lut': row 0 decreases (expected non-decreasing rows)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterable

import torch

__all__ = ["Table", "TableError", "check_tables"]

class TableError(ValueError):
    """A stored table breaks its rule (the message names the table and what was expected)."""


@dataclass(frozen=True)
class Table:
    """The rule of one stored table.

    Attributes
    ----------
    name : str
        The table's name in :meth:`~dynbtf.synthesis.base.Synthesizer.prepared_arrays`.
    dtype : torch.dtype
        Its exact dtype.
    shape : tuple of (int or None)
        Its shape; ``None`` admits any size on that axis (at least 1).
    low, high : float
        Inclusive bounds of every value (floats must also be finite).
    monotone : bool
        Rows (the last axis) are non-decreasing: inverse distribution tables.
    """

    name: str
    dtype: torch.dtype
    shape: tuple[int | None, ...]
    low: float = -math.inf
    high: float = math.inf
    monotone: bool = False

    def problem(self, value) -> str | None:
        """Why ``value`` breaks this rule, or None."""
        if not isinstance(value, torch.Tensor):
            return f"expected a tensor, got {type(value).__name__}"
        if value.dtype != self.dtype:
            return f"dtype {value.dtype}, expected {self.dtype}"
        if value.ndim != len(self.shape) or any(
                (want is None and got < 1) or (want is not None and got != want)
                for got, want in zip(value.shape, self.shape)):
            expected = "(" + ", ".join("any" if s is None else str(s) for s in self.shape) + ")"
            return f"shape {tuple(value.shape)}, expected {expected}"
        if value.numel() == 0:
            return None
        data = value.detach().cpu()
        if data.is_floating_point():
            finite = torch.isfinite(data)
            if not bool(finite.all()):
                return f"{int((~finite).sum())} non-finite values (NaN or infinity)"
        if self.dtype != torch.bool:
            low, high = data.min().item(), data.max().item()
            if low < self.low or high > self.high:
                return f"values in [{low:.6g}, {high:.6g}], expected within [{self.low:.6g}, {self.high:.6g}]"
        if self.monotone and data.ndim >= 1 and data.shape[-1] > 1:
            rows = data.reshape(-1, data.shape[-1])
            bad = (rows[:, 1:] < rows[:, :-1]).any(dim=1)
            if bool(bad.any()):
                return f"row {int(bad.nonzero()[0])} decreases (expected non-decreasing rows)"
        return None


def check_tables(arrays: dict[str, torch.Tensor], rules: Iterable[Table]) -> None:
    """Hold ``arrays`` to ``rules``: the same names (none missing, none extra), each array to its rule.

    Raises :class:`TableError` at the first table that breaks its rule.
    """
    rules = {rule.name: rule for rule in rules}
    missing = sorted(set(rules) - set(arrays))
    if missing:
        raise TableError(f"missing table{'s' if len(missing) > 1 else ''} {', '.join(map(repr, missing))}")
    extra = sorted(set(arrays) - set(rules))
    if extra:
        raise TableError(f"unexpected table{'s' if len(extra) > 1 else ''} {', '.join(map(repr, extra[:5]))} "
                         f"(expected only {', '.join(map(repr, sorted(rules))) or 'none'})")
    for name, rule in rules.items():
        problem = rule.problem(arrays[name])
        if problem is not None:
            raise TableError(f"table {name!r}: {problem}")
