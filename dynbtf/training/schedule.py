"""The learning-rate schedule of a fit, and when the fit stops.

Two schedules (``TrainConfig.schedule``):

* ``"epochs"`` -- the paper's: ``epochs`` passes over the training pairs, the learning rate
  multiplied by ``lr_decay`` after every epoch. The held-out monitor is scored once per epoch,
  for display only.
* ``"converge"`` -- set by the held-out monitor, scored every ``monitor_every`` steps. The
  learning rate is **halved whenever the monitor stalls** (:class:`PlateauRule`: no new best by
  more than 0.02 dB in 2 checks in a row), and over the last third of the ceiling (``epochs``
  epochs) it also decays steadily, exponentially, to 1/32 of its start at the ceiling (the fast
  recipe's own decay is ``0.9 ** 30 = 1/24``): the rate stays high while the monitor gains,
  which on a 64 x 64 stone reached in 7,800 steps what a decay over the whole ceiling reached in
  19,000, and a fit cut by the ceiling still ends annealed. The fit **stops at a stall once the
  rate is at most 1/16** of its start (on that stone the checks at 1/32 gained 0.01 dB more in
  1,560 more steps), never before ``min_steps``, at the latest at the ceiling; ``max_minutes`` still stops
  it as a time budget. A BTF whose monitor stalls early (a small one, or an easy one) stops early;
  one whose monitor keeps improving trains to the ceiling, which the recipe sets from the BTF's
  size (:mod:`dynbtf.training.recipe`).

With a time budget (``max_minutes``) the converge schedule's **ceiling follows the budget**: at
each held-out check after a run's first, the fit re-plans how many steps the rest of the budget
affords at the rate since the previous check, and a lower ceiling is written into that check's
record (``"ceiling"``; a ceiling is never raised). The
steady decay then runs to the floor at the lowered ceiling, so a fit the machine slowed down
still ends annealed, and a fit that reaches the lowered ceiling ends there (``"ceiling"``)
instead of being cut by the budget mid-schedule.

Both are pure functions of the monitor's record (``[{"step", "held_out_psnr", ...}, ...]``, with any
lowered ``"ceiling"``), which the checkpoint keeps: a resumed fit makes the same decisions as an
uninterrupted one.

>>> rule = PlateauRule(factor=0.5, patience=2, threshold_db=0.02, decays=1)
>>> rule.state([20.0, 21.0, 21.01, 21.0])       # two checks without a 0.02 dB gain: one halving
(1, False)
>>> rule.state([20.0, 21.0, 21.01, 21.0, 21.5, 21.4, 21.49])   # the next stall at the lowest rate: stop
(1, True)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

__all__ = ["SCHEDULES", "ANNEAL_TAIL", "ANNEAL_FLOOR", "PlateauRule", "PLATEAU", "Schedule", "make_schedule"]

#: The values of ``TrainConfig.schedule``.
SCHEDULES = ("epochs", "converge")
#: The part of the converge schedule's ceiling over which the steady decay runs (the rate is the plateau
#: rule's alone before it).
ANNEAL_TAIL = 1.0 / 3.0
#: The steady decay's factor at the ceiling.
ANNEAL_FLOOR = 1.0 / 32.0


@dataclass(frozen=True)
class PlateauRule:
    """Reduce-on-plateau: halve the rate when the held-out score stalls; stop after the last halving's stall.

    Attributes
    ----------
    factor : float
        Learning-rate factor applied at each stall (0.5).
    patience : int
        Checks in a row without a new best (by more than ``threshold_db``) that make a stall (2).
    threshold_db : float
        A check is a new best when it beats the best so far by more than this (dB; 0.02).
    decays : int
        The lowest rate is ``factor ** decays`` (4: 1/16); a stall at (or below) it stops the fit.
    """

    factor: float = 0.5
    patience: int = 2
    threshold_db: float = 0.02
    decays: int = 4

    def state(self, scores: Sequence[float], anneal: Sequence[float] | None = None) -> tuple[int, bool]:
        """``(halvings so far, stop?)`` after the held-out ``scores`` (dB, in order; NaN counts as no gain).

        ``anneal``: the rate's factor from the steady decay at each check (default 1): a stall stops the fit
        when ``factor ** halvings * anneal`` is already at most ``factor ** decays``.
        """
        best, stalled, decays = -math.inf, 0, 0
        for i, score in enumerate(scores):
            if score > best + self.threshold_db:  # False for NaN
                best, stalled = score, 0
                continue
            stalled += 1
            if stalled >= self.patience:
                rate = self.factor ** decays * (1.0 if anneal is None else anneal[i])
                if rate <= self.factor ** self.decays * (1 + 1e-9):
                    return decays, True
                decays, stalled = decays + 1, 0
        return decays, False

    def describe(self) -> str:
        """One line: the rule in words."""
        return (f"lr x{self.factor:g} when {self.patience} held-out checks in a row gain no more than "
                f"{self.threshold_db:g} dB, stop at such a stall once lr is x{self.factor ** self.decays:g}")


#: The rule of ``schedule="converge"``.
PLATEAU = PlateauRule()


class Schedule:
    """The learning-rate multiplier, monitor timing and stopping of one fit (see the module docstring).

    Parameters
    ----------
    kind : str
        ``"epochs"`` or ``"converge"``.
    epochs : int
        The fit's epochs (``"converge"``: the ceiling, in whole epochs).
    steps_per_epoch : int
    lr_decay : float
        Factor per epoch (``"epochs"`` only).
    monitor_every : int
        Steps between held-out checks (``"converge"``; 0: once per epoch).
    min_steps : int
        Fewest steps before ``"converge"`` may stop.
    rule : PlateauRule
    """

    def __init__(self, kind: str, *, epochs: int, steps_per_epoch: int, lr_decay: float = 0.9,
                 monitor_every: int = 0, min_steps: int = 0, rule: PlateauRule = PLATEAU) -> None:
        if kind not in SCHEDULES:
            raise ValueError(f"schedule: expected one of {SCHEDULES}, got {kind!r}")
        self.kind, self.epochs, self.steps_per_epoch = kind, int(epochs), int(steps_per_epoch)
        self.lr_decay, self.min_steps, self.rule = float(lr_decay), int(min_steps), rule
        self.monitor_every = int(monitor_every) if kind == "converge" and monitor_every > 0 else 0
        self.total_steps = self.epochs * self.steps_per_epoch

    def monitor_due(self, done_steps: int, epoch_ended: bool) -> bool:
        """Whether the held-out monitor is scored after step ``done_steps`` (1-based count of steps done)."""
        if self.monitor_every:
            return done_steps % self.monitor_every == 0 or done_steps >= self.total_steps
        return epoch_ended

    def anneal(self, done_steps: int, ceiling: int | None = None) -> float:
        """``"converge"``: the steady part of the rate's factor after ``done_steps`` steps: 1 until the last
        :data:`ANNEAL_TAIL` of the ceiling (``ceiling`` steps, default the epochs' :attr:`total_steps`), then an
        exponential decay to :data:`ANNEAL_FLOOR` at the ceiling."""
        total = self.total_steps if ceiling is None else min(int(ceiling), self.total_steps)
        start = (1.0 - ANNEAL_TAIL) * total
        progress = (min(done_steps, total) - start) / max(total - start, 1)
        return ANNEAL_FLOOR ** max(progress, 0.0)

    def ceilings(self, record: Sequence[dict[str, Any]]) -> list[int]:
        """The ceiling in force after each check of ``record``: :attr:`total_steps`, lowered by any check's
        ``"ceiling"`` (a time budget's re-plan) from that check on."""
        out, ceiling = [], self.total_steps
        for r in record:
            ceiling = min(ceiling, int(r.get("ceiling", ceiling)))
            out.append(ceiling)
        return out

    def ceiling(self, record: Sequence[dict[str, Any]]) -> int:
        """The step at which the fit ends at the latest, after the checks of ``record``."""
        return self.ceilings(record)[-1] if record else self.total_steps

    def _plateau(self, record: Sequence[dict[str, Any]]) -> tuple[int, bool]:
        return self.rule.state([r["held_out_psnr"] for r in record],
                               [self.anneal(r["step"], c) for r, c in zip(record, self.ceilings(record))])

    def lr_multiplier(self, epoch: int, done_steps: int, record: Sequence[dict[str, Any]]) -> float:
        """Factor on every group's initial learning rate for the next step (after ``done_steps`` steps, in
        ``epoch``)."""
        if self.kind == "epochs":
            return self.lr_decay ** epoch
        return self.rule.factor ** self._plateau(record)[0] * self.anneal(done_steps, self.ceiling(record))

    def converged(self, done_steps: int, record: Sequence[dict[str, Any]]) -> bool:
        """``"converge"``: the monitor's record says stop (and ``min_steps`` are done)."""
        if self.kind != "converge" or done_steps < self.min_steps:
            return False
        return self._plateau(record)[1]

    def replan(self, done_steps: int, affordable_steps: float, record: Sequence[dict[str, Any]]) -> int | None:
        """``"converge"`` under a time budget, at a check after ``done_steps`` steps: the lowered ceiling when the
        rest of the budget affords only ``affordable_steps`` more steps (the fit ends there, annealed), else None."""
        if self.kind != "converge":
            return None
        planned = done_steps + max(int(affordable_steps), 0)
        return planned if planned < self.ceiling(record) else None

    def describe(self) -> str:
        """One line for logs and the recipe summary."""
        if self.kind == "epochs":
            return f"{self.epochs} epochs x {self.steps_per_epoch} steps, lr x{self.lr_decay:.3g} per epoch"
        every = self.monitor_every or self.steps_per_epoch
        tail = round((1.0 - ANNEAL_TAIL) * self.total_steps)
        return (f"until the held-out monitor stops improving (checked every {every} steps; {self.rule.describe()}; "
                f"from step {tail} lr also decays steadily to x{ANNEAL_FLOOR:g} at the ceiling), "
                f"at least {self.min_steps} and at most {self.total_steps} steps")


def make_schedule(config, steps_per_epoch: int) -> Schedule:
    """The :class:`Schedule` of a :class:`~dynbtf.training.fit.TrainConfig`."""
    return Schedule(config.schedule, epochs=config.epochs, steps_per_epoch=steps_per_epoch,
                    lr_decay=config.lr_decay, monitor_every=config.monitor_every, min_steps=config.min_steps)
