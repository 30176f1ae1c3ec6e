"""``dynbtf fit --repr auto`` (the default): the representation chosen by stereo evidence and a held-out race.

Which model is best depends on the material: the Triple Plane with parallax gains 4-8 dB on
materials with relief and loses 2 dB on a flat, glossy one (docs/parallax.md). The **stereo
height estimate** the parallax model starts from is computed first: where it is trusted on at
least :data:`DECISIVE_RELIEF` of the texels (a relief the views agree on over most of the
surface), the parallax model is chosen without a trial. Otherwise each candidate kind
(:data:`CANDIDATES`) trains a **trial** of :data:`TRIAL_CHECKS` held-out checks
(``TRIAL_CHECKS x monitor_every`` steps, the first part of its own schedule: same recipe, seed,
held-out pairs and monitor), and the best held-out PSNR at the trial's end wins; a kind
listed later must beat the ones before it by :data:`MARGIN_DB` (0.5 dB; the first kind, the
Triple Plane, is the cheaper to render, and an early lead smaller than that did not last on a
flat, glossy material). A trial that leaves the two within the margin of each other is undecided
(leather and lacquered wood both score 26.8 dB for both kinds there, and the parallax model ends
4.6 dB ahead on one and 2 dB behind on the other); the stereo estimate decides it: the parallax
model wins where the estimate was trusted on at least :data:`TRUSTED_RELIEF` of the texels. The
**winner's fit continues from its trial** (its checkpoint becomes the output's), so only the losers'
trials are extra work.

The choice is printed in one line and recorded in the model's provenance
(``representation_choice``: the stereo's trusted fraction and each trial's steps, held-out PSNR
and seconds). A re-run on the same output continues the chosen kind (it is read from the
checkpoint, or from the finished model file); an interrupted race continues its trials (each from
its checkpoint, the finished ones recorded next to the output). ``max_minutes`` is the whole
command's budget, stereo and trials included.

>>> from dynbtf.training.model_choice import pick
>>> pick({"triple": 24.0, "triple-parallax": 24.05})    # within the margin: the cheaper kind
'triple'
>>> pick({"triple": 24.0, "triple-parallax": 27.4})
'triple-parallax'
"""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
import time
from pathlib import Path
from typing import Any

from ..data.base import BTFSource
from ..errors import DynBTFError, InputError
from ..device import resolve_device
from .checkpoint import checkpoint_path
from .distributed import from_environment
from .fit import FitResult, TrainConfig
from .fitters import get_fitter, parallax_stereo_options, register_fitter

__all__ = ["DEFAULT_KIND", "CANDIDATES", "TRIAL_CHECKS", "MARGIN_DB", "RELIEF_KIND", "TRUSTED_RELIEF",
           "DECISIVE_RELIEF", "pick", "fit_best", "kind_in_progress", "stereo_fitter_options"]

#: The kind ``dynbtf fit`` and ``dynbtf fit-many`` fit when none is named.
DEFAULT_KIND = "auto"
#: The kinds ``--repr auto`` chooses among, cheapest to render first.
CANDIDATES = ("triple", "triple-parallax")
#: Held-out checks (of ``monitor_every`` steps each) in a trial.
TRIAL_CHECKS = 3
#: dB by which a later candidate must beat every earlier one at the trial's end. A real relief shows as a lead of
#: several dB there (the 64 x 64 stone on the UBO2014 grid: 4.4 dB); the flat, glossy lacquered wood, which the parallax
#: model ends 2 dB *behind*, gives it a 0.2 dB lead at the trial (its extra input channel), so 0.1 chose wrongly.
MARGIN_DB = 0.5
#: The candidate with a height field, whose stereo estimate :func:`pick` weighs when the trial is undecided.
RELIEF_KIND = "triple-parallax"
#: Fraction of texels on which the stereo height must be trusted for an undecided trial to go to the parallax
#: model. Measured on the simulated materials at 128 x 128, the three undecided trials: leather 0.45 (the parallax
#: model ends 4.6 dB ahead of the Triple Plane), ceramic tiles 0.28 (flat glossy tiles, narrow joints: it ends
#: 1.7 dB behind) and lacquered wood 0.002 (2 dB behind); woven fabric 0.71, stone 0.88 and brick wall 0.84, whose
#: trials are decided anyway. The threshold sits between the tiles and the leather; it rests on those three.
TRUSTED_RELIEF = 0.35
#: Fraction of trusted texels at which the stereo estimate decides alone, before any trial: the parallax model,
#: without a trial of the Triple Plane. Every simulated material measured with that much trusted relief ended
#: better with parallax (stone 0.86-0.88, brick wall 0.84, woven fabric 0.71: by 2.7-8 dB) and every material
#: that ended better flat had at most 0.28 (the ceramic tiles); the leather (0.45, parallax 4.6 dB ahead) is
#: left to the race.
DECISIVE_RELIEF = 0.6


class _TrialOver(Exception):
    """Raised by the trial's step callback once the trial's last held-out check is done."""


def pick(scores: dict[str, float], stereo_trusted: float | None = None) -> str:
    """The winning kind of ``scores`` (held-out PSNR per kind, in :data:`CANDIDATES` order): the first kind
    unless a later one beats the best so far by more than :data:`MARGIN_DB` (NaN never wins). When the trial
    leaves the Triple Plane and the parallax model within the margin of each other, the stereo estimate decides:
    the parallax model wins if it was trusted on at least :data:`TRUSTED_RELIEF` of the texels
    (``stereo_trusted``, the fraction; None: no such evidence).

    >>> pick({"triple": 26.86, "triple-parallax": 26.82}, stereo_trusted=0.6)   # undecided, a trusted relief
    'triple-parallax'
    >>> pick({"triple": 26.71, "triple-parallax": 26.81}, stereo_trusted=0.01)  # undecided, no relief
    'triple'
    """
    winner, best = None, -math.inf
    for kind, score in scores.items():
        if winner is None or score > best + MARGIN_DB:
            winner, best = kind, (score if math.isfinite(score) else -math.inf)
    relief = scores.get(RELIEF_KIND, math.nan)
    if (winner != RELIEF_KIND and stereo_trusted is not None and stereo_trusted >= TRUSTED_RELIEF
            and relief >= best - MARGIN_DB):  # (False for NaN)
        return RELIEF_KIND
    return winner


def stereo_fitter_options(kind: str, max_height: float | None, option: str = "--stereo-max-height") -> dict:
    """The fitter keywords that set the stereo search range ``max_height`` (uv units) for ``--repr kind``: ``{}``
    without one; :class:`InputError` naming ``option`` for a kind without a height field."""
    if max_height is None:
        return {}
    if kind not in ("triple-parallax", "auto"):
        raise InputError(f"{option} applies to --repr triple-parallax (or auto), not {kind!r}")
    stereo = {"stereo": {"max_height": max_height}}
    return {"kind_options": {"triple-parallax": stereo}} if kind == "auto" else stereo


def kind_in_progress(output) -> str | None:
    """The kind an earlier ``--repr auto`` run on ``output`` chose: from its checkpoint (unfinished) or from the
    finished model file's metadata; None when there is neither."""
    import torch

    from ..representations.model_file import read_model_metadata

    ckpt = checkpoint_path(output)
    if ckpt.exists():
        try:
            state = torch.load(ckpt, map_location="cpu", weights_only=True)
            kind = state.get("fingerprint", {}).get("kind")
        except Exception:
            kind = None  # a damaged checkpoint: the fitter of the race's first kind reports it
        return kind if kind in CANDIDATES else None
    if Path(output).is_file():
        try:
            kind = read_model_metadata(output).get("kind")
        except DynBTFError:
            return None
        return kind if kind in CANDIDATES else None
    return None


def _trial_output(output: Path, kind: str) -> Path:
    return output.with_name(f".{output.name}.trial-{kind}.dbtfm")


def _race_path(output: Path) -> Path:
    """The finished trials of an unfinished race (JSON), so that a re-run continues the race."""
    return output.with_name(f".{output.name}.race.json")


def _finished_trials(output: Path) -> dict[str, dict[str, Any]]:
    """The trials an earlier, interrupted race on ``output`` finished (``{}`` when none, or unreadable)."""
    import json

    try:
        trials = json.loads(_race_path(output).read_text())
    except (OSError, ValueError):
        return {}
    ok = isinstance(trials, dict) and all(k in CANDIDATES and isinstance(t, dict) and
                                          isinstance(t.get("held_out_psnr"), float) for k, t in trials.items())
    return trials if ok else {}


def _checks_in_checkpoint(path: Path) -> list[tuple[float, int]]:
    """The held-out checks ``(score, step)`` recorded in a trial's checkpoint (none without one)."""
    import torch

    if not path.exists():
        return []
    try:
        record = torch.load(path, map_location="cpu", weights_only=True).get("monitor", [])
        return [(float(r["held_out_psnr"]), int(r["step"])) for r in record]
    except Exception:
        return []  # a damaged checkpoint: the trial's fitter reports it


def _run_trial(kind: str, source: BTFSource, output: Path, config: TrainConfig, progress: bool,
               options: dict[str, Any], callback=None) -> tuple[dict[str, Any] | None, FitResult | None]:
    """Train ``kind`` into its trial output until its :data:`TRIAL_CHECKS`-th held-out check (or the end of a shorter
    fit; an interrupted trial continues from its checkpoint). Returns ``({"held_out_psnr", "steps", "seconds",
    "seconds_per_step"}, None)`` at that check (``seconds_per_step``: the mean of the optimizer steps run in this
    call, set-up and checks not counted), or ``(None, result)`` when the time budget stopped the trial first.
    ``callback`` (the caller's per-step callback) sees the trial's steps too."""
    checks = _checks_in_checkpoint(checkpoint_path(_trial_output(output, kind)))
    timed = [0, 0.0]  # optimizer steps run in this call, their seconds

    def stop_after_trial(info: dict[str, Any]) -> None:
        if callback is not None:
            callback(info)
        timed[0] += 1
        timed[1] += float(info.get("step_seconds", 0.0))
        if "held_out_psnr" in info:
            checks.append((info["held_out_psnr"], info["global_step"]))
            if len(checks) >= TRIAL_CHECKS:
                raise _TrialOver

    start = time.perf_counter()
    if len(checks) < TRIAL_CHECKS:
        try:
            result = get_fitter(kind)(source, _trial_output(output, kind), config, progress=progress,
                                      callback=stop_after_trial, **options)
            if not result.finished:
                return None, result
        except _TrialOver:
            pass
    score, steps = checks[min(len(checks), TRIAL_CHECKS) - 1] if checks else (math.nan, 0)
    record = {"held_out_psnr": score, "steps": steps, "seconds": round(time.perf_counter() - start, 1)}
    if timed[0]:
        record["seconds_per_step"] = timed[1] / timed[0]  # the optimizer steps alone (no set-up, no checks)
    return record, None


def _stereo_estimate(source: BTFSource, options: dict[str, Any], progress: bool):
    """``(height, trusted)`` of the stereo sweep the parallax fitter would run with ``options``
    (:func:`~dynbtf.training.fitters.parallax_stereo_options`)."""
    from .stereo_height import stereo_height

    stereo = parallax_stereo_options(source, options.get("stereo"))
    return stereo_height(source, progress=progress, return_trusted=True, **stereo)


def _remaining(config: TrainConfig, start: float) -> TrainConfig:
    """``config`` with ``max_minutes`` less the minutes since ``start`` (the whole command's budget)."""
    if config.max_minutes is None:
        return config
    left = config.max_minutes - (time.perf_counter() - start) / 60
    return dataclasses.replace(config, max_minutes=max(left, 1e-9))


def _promote(output: Path, winner: str) -> None:
    """Make the winner's trial the output's fit (checkpoint and model file); delete every trial and the race."""
    trial = _trial_output(output, winner)
    for made, final in ((checkpoint_path(trial), checkpoint_path(output)), (trial, output)):
        if made.exists():
            shutil.move(made, final)
    for kind in CANDIDATES:
        _trial_output(output, kind).unlink(missing_ok=True)
        checkpoint_path(_trial_output(output, kind)).unlink(missing_ok=True)
    _race_path(output).unlink(missing_ok=True)


def fit_best(source: BTFSource, output, config: TrainConfig | None = None, *, progress: bool = True,
             callback=None, kind_options: dict[str, dict[str, Any]] | None = None) -> FitResult:
    """``dynbtf fit --repr auto``: the stereo evidence, a race of :data:`CANDIDATES` unless it decides (see the
    module docstring), then the winner's fit.

    Parameters
    ----------
    source, output, config, progress, callback :
        As any fitter (:mod:`dynbtf.training.fitters`); ``callback`` sees every step, the trials' included;
        ``config.max_minutes`` is the whole command's budget (stereo and trials included): when it runs out during
        a trial, that trial's result (unfinished) is returned, and the same call again continues the race.
    kind_options : dict, optional
        Fitter options per kind (e.g. ``{"triple-parallax": {"stereo": {...}}}``).

    Returns
    -------
    FitResult
        Of the winner; its model file's provenance holds ``representation_choice``.
    """
    from ..io import atomic_path

    config = (config or TrainConfig()).validate()
    output, kind_options, start = Path(output), dict(kind_options or {}), time.perf_counter()
    if config.held_out_fraction <= 0 or config.monitor_pairs <= 0:
        raise InputError("--repr auto chooses by held-out PSNR: it needs held-out pairs (--held-out-fraction > 0); "
                         f"name a kind instead, one of {list(CANDIDATES)}")
    chosen = kind_in_progress(output)
    if chosen is not None:
        if progress:
            print(f"representation: {chosen} (chosen by the earlier run on {output}; continuing it)")
        return get_fitter(chosen)(source, output, config, progress=progress, callback=callback,
                                  **kind_options.get(chosen, {}))
    parallel, _ = from_environment(resolve_device(config.device))  # (a data-parallel fit: every process races)
    progress = progress and parallel.is_main
    trials = _finished_trials(output)
    if progress:
        print(f"choosing the representation: the stereo height estimate, then, unless it is trusted on at least "
              f"{DECISIVE_RELIEF:.0%} of the texels, a trial of {TRIAL_CHECKS} held-out checks each of "
              f"{', '.join(CANDIDATES)} on the same held-out pairs"
              + (f" (continuing the race: {', '.join(trials)} done)" if trials else ""))
    # the stereo estimate first (computed once: it may decide alone, and its height starts the parallax fit; a
    # parallax trial resumed from its checkpoint keeps its own height, the sweep is then evidence alone)
    relief_options = dict(kind_options.get(RELIEF_KIND, {}))
    relief_options["stereo_estimate"] = _stereo_estimate(source, relief_options, progress)
    trusted = float(relief_options["stereo_estimate"][1].double().mean())
    options_of = {kind: (relief_options if kind == RELIEF_KIND else dict(kind_options.get(kind, {})))
                  for kind in CANDIDATES}
    if trusted >= DECISIVE_RELIEF:
        winner = RELIEF_KIND
        rule = (f"{RELIEF_KIND} without a trial where the stereo height is trusted on at least "
                f"{DECISIVE_RELIEF:.0%} of the texels")
        if progress:
            print(f"representation: {winner} (stereo height trusted on {trusted:.0%} of the texels; {rule})")
        evidence = {"kind": winner, "rule": rule, "stereo_trusted": trusted, "trials": trials}
        return _continue_winner(source, output, _remaining(config, start), winner, evidence, options_of[winner],
                                parallel, progress, callback)
    for kind in CANDIDATES:
        if kind not in trials:
            trial, stopped = _run_trial(kind, source, output, _remaining(config, start), progress, options_of[kind],
                                        callback)
            if stopped is not None:
                if progress:
                    print(f"time budget reached during the trial of {kind}; run the same command again to continue")
                return stopped
            trials[kind] = trial | ({"stereo_trusted": trusted} if kind == RELIEF_KIND else {})
            if parallel.is_main:
                with atomic_path(_race_path(output)) as tmp:
                    tmp.write_text(json.dumps(trials))
    winner = pick({k: t["held_out_psnr"] for k, t in trials.items()}, trusted)
    rule = (f"a kind after {CANDIDATES[0]} must win by {MARGIN_DB:g} dB; within that, {RELIEF_KIND} wins where the "
            f"stereo height is trusted on at least {TRUSTED_RELIEF:.0%} of the texels")
    if progress:
        print(f"representation: {winner} (held-out PSNR after a trial of "
              + ", ".join(f"{k} {t['held_out_psnr']:.2f} dB at step {t['steps']}" for k, t in trials.items())
              + f"; stereo height trusted on {trusted:.0%} of the texels; {rule})")
    evidence = {"kind": winner, "rule": f"best held-out PSNR at the last of {TRIAL_CHECKS} held-out checks of a "
                                        f"trial of each kind; {rule}", "stereo_trusted": trusted, "trials": trials}
    return _continue_winner(source, output, _remaining(config, start), winner, evidence, options_of[winner],
                            parallel, progress, callback)


def _continue_winner(source: BTFSource, output: Path, config: TrainConfig, winner: str, evidence: dict[str, Any],
                     options: dict[str, Any], parallel, progress: bool, callback) -> FitResult:
    """The winner's fit, continued from its trial if it had one (whose checkpoint or finished model becomes the
    output's), with ``evidence`` as its provenance's ``representation_choice``."""
    parallel.barrier()  # every trial's checkpoint is written
    if parallel.is_main:
        _promote(output, winner)
    if output.is_file() and parallel.is_main:  # the trial was the whole fit (a short schedule): add the evidence
        from ..representations.model_file import load_model, save_model

        rep, meta = load_model(output, device="cpu")
        save_model(output, rep, meta["provenance"] | {"representation_choice": evidence})
    parallel.barrier()
    return get_fitter(winner)(source, output, config, progress=progress, callback=callback,
                              extra_provenance={"representation_choice": evidence}, **options)


register_fitter("auto")(fit_best)
