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
its checkpoint, the finished ones recorded next to the output).

**A time budget** (``max_minutes``) is the whole command's, counted from its start: the stereo, the
trials and the winner's fit. The trials then take at most :data:`RACE_SHARE` of what the stereo
leaves: the first one's measured step time sizes both (fewer steps than a full trial when the budget
is short, the same number for each kind, so both are scored at the same step). A budget that
affords fewer than :data:`MIN_TRIAL_STEPS` steps per trial leaves the choice to the stereo estimate
(the parallax model from :data:`TRUSTED_RELIEF` trusted texels), and a budget that runs out during a
trial writes the leader so far; either way the choice and why is one line, and the output is a model.

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
#: Under a time budget, the fraction of the budget left after the stereo estimate that the trials may take together.
RACE_SHARE = 0.3
#: A parallax step's cost in Triple Plane steps, for sizing the second trial from the first one's step time
#: (kept above what benchmarks/bench_parallax_training.py measures: the visible-point table grows during a trial).
RELIEF_STEP_COST = 1.5
#: Timed steps of the first trial before a time budget sizes the trials.
SIZING_STEPS = 10
#: Fewest steps a trial must have for the race to decide; a budget affording fewer leaves it to the stereo estimate.
MIN_TRIAL_STEPS = 100
#: Seconds of budget below which the leader of an unfinished race is written as its trial left it (no more training).
LEADER_MIN_SECONDS = 5.0
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


def _run_trial(kind: str, source: BTFSource, output: Path, config: TrainConfig, progress: bool,
               options: dict[str, Any], steps: int | None, sizer=None, callback=None) -> dict[str, Any]:
    """Train ``kind`` into its trial output for ``steps`` optimizer steps (or until ``sizer``, given the mean
    seconds of the first timed steps, returns the count; an interrupted trial continues from its checkpoint), then
    score its model on the held-out monitor. Returns ``{"held_out_psnr", "steps", "seconds", "seconds_per_step",
    "complete"}``: ``complete`` is False when the time budget stopped the trial first (its model file is written
    either way). ``callback`` (the caller's per-step callback) sees the trial's steps too."""
    from .fit import StopTraining, _image_store, predict_images
    from .images import held_out_split
    from .monitor import HeldOutMonitor

    timed = [0, 0.0, 0, None]  # steps timed in this call (the first, with the set-up, left out), their seconds,
    target = [steps]             # the last step, the seconds from the start to the end of the first step

    def stop_after_trial(info: dict[str, Any]) -> None:
        if callback is not None:
            callback(info)
        timed[2] = info["global_step"]
        if timed[3] is None:
            timed[3] = time.perf_counter() - start
        else:
            timed[0] += 1
            timed[1] += float(info.get("step_seconds", 0.0))
        if target[0] is None and timed[0] >= SIZING_STEPS:
            target[0] = max(timed[2] + 1, sizer(timed[1] / timed[0], timed[2], timed[3]))
            if progress:
                print(f"trial of {kind}: {target[0]} steps (sized to the time budget at "
                      f"{1e3 * timed[1] / timed[0]:.3g} ms per step)")
        if target[0] is not None and info["global_step"] >= target[0]:
            raise StopTraining(f"the trial's {target[0]} steps are done")

    start = time.perf_counter()
    result = get_fitter(kind)(source, _trial_output(output, kind), config, progress=progress,
                              callback=stop_after_trial, **options)
    done = int(result.metadata.get("provenance", {}).get("schedule", {}).get("steps", timed[2]))
    _, held_out = held_out_split(source.n_views, source.n_lights, config.held_out_fraction, config.seed)
    monitor = HeldOutMonitor(_image_store(source, config), held_out, config.monitor_pairs, config.seed,
                             result.representation.positional_plane().device)  # the fit's own monitor, at its end
    score = monitor.score(result.representation, predict_images)
    record = {"held_out_psnr": score, "steps": done, "seconds": round(time.perf_counter() - start, 1),
              "complete": bool(result.finished or (target[0] is not None and done >= target[0]))}
    if timed[0]:
        record["seconds_per_step"] = timed[1] / timed[0]  # the optimizer steps alone (no set-up, no checks)
    return record


def _stereo_estimate(source: BTFSource, options: dict[str, Any], progress: bool):
    """``(height, trusted)`` of the stereo sweep the parallax fitter would run with ``options``
    (:func:`~dynbtf.training.fitters.parallax_stereo_options`)."""
    from .stereo_height import stereo_height

    stereo = parallax_stereo_options(source, options.get("stereo"))
    return stereo_height(source, progress=progress, return_trusted=True, **stereo)


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
             callback=None, kind_options: dict[str, dict[str, Any]] | None = None,
             started: float | None = None) -> FitResult:
    """``dynbtf fit --repr auto``: the stereo evidence, a race of :data:`CANDIDATES` unless it decides (see the
    module docstring), then the winner's fit.

    Parameters
    ----------
    source, output, config, progress, callback :
        As any fitter (:mod:`dynbtf.training.fitters`); ``callback`` sees every step, the trials' included;
        ``config.max_minutes`` is the whole command's budget, counted from ``started``: the stereo, the trials
        (sized to take at most :data:`RACE_SHARE` of what the stereo leaves) and the winner's fit. When it runs
        out during the race, the leader so far is written (its choice stated in one line), and the same call
        again continues its fit.
    kind_options : dict, optional
        Fitter options per kind (e.g. ``{"triple-parallax": {"stereo": {...}}}``).
    started : float, optional
        ``time.perf_counter()`` when the command started (default: now).

    Returns
    -------
    FitResult
        Of the winner; its model file's provenance holds ``representation_choice``.
    """
    from .fit import shared_image_cache

    if config is not None and config.subtexel:
        raise InputError("--subtexel (TrainConfig.subtexel) applies to the Triple Plane only, and --repr auto races "
                         "it against triple-parallax, which has none: give --repr triple with --subtexel")
    with shared_image_cache():  # the trials and the winner's fit decode the BTF once
        return _fit_best(source, output, config, progress=progress, callback=callback, kind_options=kind_options,
                         started=started)


def _fit_best(source: BTFSource, output, config: TrainConfig | None, *, progress: bool, callback,
              kind_options: dict[str, dict[str, Any]] | None, started: float | None) -> FitResult:
    from ..io import atomic_path
    from .fit import budget_left, steps_after_this_fit

    started = time.perf_counter() if started is None else started
    config = (config or TrainConfig()).validate()
    output, kind_options = Path(output), dict(kind_options or {})
    if config.held_out_fraction <= 0 or config.monitor_pairs <= 0:
        raise InputError("--repr auto chooses by held-out PSNR: it needs held-out pairs (--held-out-fraction > 0); "
                         f"name a kind instead, one of {list(CANDIDATES)}")
    chosen = kind_in_progress(output)
    if chosen is not None:
        if progress:
            print(f"representation: {chosen} (chosen by the earlier run on {output}; continuing it)")
        return get_fitter(chosen)(source, output, budget_left(config, started), progress=progress,
                                  callback=callback, **kind_options.get(chosen, {}))
    parallel, _ = from_environment(resolve_device(config.device))  # (a data-parallel fit: every process races)
    progress = progress and parallel.is_main
    trials = _finished_trials(output)
    full_trial = TRIAL_CHECKS * _monitor_interval(source, config)
    winner_steps = config.epochs * _monitor_interval(source, dataclasses.replace(config, monitor_every=0))
    if progress:
        print(f"choosing the representation: the stereo height estimate, then, unless it is trusted on at least "
              f"{DECISIVE_RELIEF:.0%} of the texels, a trial of {full_trial} steps ({TRIAL_CHECKS} held-out checks"
              + (", fewer if the time budget is short" if config.max_minutes is not None else "")
              + f") each of {', '.join(CANDIDATES)} on the same held-out pairs"
              + (f" (continuing the race: {', '.join(trials)} done)" if trials else ""))
    # the stereo estimate first (computed once: it may decide alone, and its height starts the parallax fit; a
    # parallax trial resumed from its checkpoint keeps its own height, the sweep is then evidence alone)
    relief_options = dict(kind_options.get(RELIEF_KIND, {}))
    relief_options["stereo_estimate"] = _stereo_estimate(source, relief_options, progress)
    trusted = float(relief_options["stereo_estimate"][1].double().mean())
    options_of = {kind: (relief_options if kind == RELIEF_KIND else dict(kind_options.get(kind, {})))
                  for kind in CANDIDATES}

    def decided(winner: str, rule: str, line: str) -> FitResult:
        if progress:
            print(f"representation: {winner} ({line})")
        evidence = {"kind": winner, "rule": rule, "stereo_trusted": trusted, "trials": trials}
        return _continue_winner(source, output, budget_left(config, started), winner, evidence, options_of[winner],
                                parallel, progress, callback)

    if trusted >= DECISIVE_RELIEF:
        rule = (f"{RELIEF_KIND} without a trial where the stereo height is trusted on at least "
                f"{DECISIVE_RELIEF:.0%} of the texels")
        return decided(RELIEF_KIND, rule, f"stereo height trusted on {trusted:.0%} of the texels; {rule}")
    # the trials' length: the full trial, or what RACE_SHARE of the budget left affords (sized in the first trial
    # from its measured step time; the second gets the same steps, so that both are scored at the same step)
    race_end = None if config.max_minutes is None else \
        time.perf_counter() + RACE_SHARE * budget_left(config, started).max_minutes * 60
    steps = next((t["steps"] for t in trials.values()), None if race_end is not None else full_trial)

    def sizer(step_seconds: float, done: int, setup_seconds: float) -> int:
        """Steps K of each trial, from the first trial's step time after ``done`` steps: the rest of the first
        trial and the whole second one (its steps RELIEF_STEP_COST times as dear, its set-up as long as the
        first's, which decoded the BTF) end by race_end."""
        left = race_end - time.perf_counter() - setup_seconds
        return int(min(full_trial, max((left + done * step_seconds) / (step_seconds * (1 + RELIEF_STEP_COST)), 1)))

    for kind in CANDIDATES:
        if kind in trials:
            continue
        if steps is not None and race_end is not None and len(trials) == 0 and steps < MIN_TRIAL_STEPS:
            break
        trial_steps = steps or full_trial  # (sized during the first trial under a budget)
        later = (len(CANDIDATES) - len(trials) - 1) * trial_steps + max(winner_steps - trial_steps, 0)
        with steps_after_this_fit(later, stop_at=trial_steps):
            trial = _run_trial(kind, source, output, budget_left(config, started), progress, options_of[kind], steps,
                               sizer, callback)
        trials[kind] = trial | ({"stereo_trusted": trusted} if kind == RELIEF_KIND else {})
        steps = steps or trial["steps"]
        if parallel.is_main:
            with atomic_path(_race_path(output)) as tmp:
                tmp.write_text(json.dumps(trials))
        if not trial["complete"]:
            break
        if race_end is not None and steps < MIN_TRIAL_STEPS:
            break  # the budget affords no real trial: the stereo decides (below)
    if len(trials) < len(CANDIDATES) or not all(t["complete"] for t in trials.values()):
        return _write_leader(source, output, config, trials, trusted, parallel, progress, started, options_of,
                             callback)
    winner = pick({k: t["held_out_psnr"] for k, t in trials.items()}, trusted)
    rule = (f"a kind after {CANDIDATES[0]} must win by {MARGIN_DB:g} dB; within that, {RELIEF_KIND} wins where the "
            f"stereo height is trusted on at least {TRUSTED_RELIEF:.0%} of the texels")
    line = ("held-out PSNR after a trial of "
            + ", ".join(f"{k} {t['held_out_psnr']:.2f} dB at step {t['steps']}" for k, t in trials.items())
            + f"; stereo height trusted on {trusted:.0%} of the texels; {rule}")
    return decided(winner, f"best held-out PSNR at the end of a trial of {steps} steps of each kind; {rule}", line)


def _monitor_interval(source: BTFSource, config: TrainConfig) -> int:
    """Steps between the held-out checks of ``config``'s schedule on ``source`` (an epoch when it names none)."""
    from .images import held_out_split

    if config.monitor_every:
        return int(config.monitor_every)
    train_pairs, _ = held_out_split(source.n_views, source.n_lights, config.held_out_fraction, config.seed)
    return math.ceil(len(train_pairs) / config.images_per_step)


def _write_leader(source: BTFSource, output: Path, config: TrainConfig, trials: dict[str, dict[str, Any]],
                  trusted: float, parallel, progress: bool, started: float, options_of, callback) -> FitResult:
    """The race did not finish in the time budget (or the budget affords no real trial): the leader so far becomes
    the output, stated in one line; the fit goes on in what is left of the budget, if anything."""
    from .fit import budget_left

    run = {k: t for k, t in trials.items() if t["steps"] > 0}
    if len(run) == len(CANDIDATES) and all(t["steps"] >= MIN_TRIAL_STEPS for t in run.values()):
        leader = pick({k: t["held_out_psnr"] for k, t in run.items()}, trusted)
        why = ("the time budget ran out during the race; the leader so far: "
               + ", ".join(f"{k} {t['held_out_psnr']:.2f} dB at step {t['steps']}" for k, t in run.items()))
    else:
        leader = RELIEF_KIND if trusted >= TRUSTED_RELIEF else CANDIDATES[0]
        why = (f"the time budget leaves no room for a race of at least {MIN_TRIAL_STEPS} steps per kind; the stereo "
               f"height estimate decides: trusted on {trusted:.0%} of the texels, {RELIEF_KIND} from "
               f"{TRUSTED_RELIEF:.0%}")
    if progress:
        print(f"representation: {leader} ({why})")
    evidence = {"kind": leader, "rule": why, "stereo_trusted": trusted, "trials": trials, "race_finished": False}
    for kind in CANDIDATES:  # the losers' trials are not kept
        if kind != leader:
            _trial_output(output, kind).unlink(missing_ok=True)
            checkpoint_path(_trial_output(output, kind)).unlink(missing_ok=True)
    left = budget_left(config, started)
    return _continue_winner(source, output, left, leader, evidence, options_of[leader], parallel, progress, callback,
                            train=left.max_minutes * 60 > LEADER_MIN_SECONDS)


def _continue_winner(source: BTFSource, output: Path, config: TrainConfig, winner: str, evidence: dict[str, Any],
                     options: dict[str, Any], parallel, progress: bool, callback, train: bool = True) -> FitResult:
    """The winner's fit, continued from its trial if it had one (whose checkpoint and model file become the
    output's), with ``evidence`` as its provenance's ``representation_choice``. ``train=False``: the trial's model
    (with the evidence) is the result as it is; its checkpoint stays for a later run to continue."""
    parallel.barrier()  # every trial's checkpoint is written
    if parallel.is_main:
        _promote(output, winner)
    if output.is_file() and parallel.is_main:  # the trial's model (a whole fit, or where it stopped): the evidence
        from ..representations.model_file import load_model, save_model

        rep, meta = load_model(output, device="cpu")
        save_model(output, rep, meta["provenance"] | {"representation_choice": evidence})
    parallel.barrier()
    if not train and output.is_file():
        from ..representations.model_file import load_model

        rep, meta = load_model(output, device="cpu")
        if progress:
            print(f"wrote {output} (the {winner} trial's model; run the same command again to continue its fit)")
        return FitResult(output, rep, meta, list(meta["provenance"].get("history", [])), False)
    return get_fitter(winner)(source, output, config, progress=progress, callback=callback,
                              extra_provenance={"representation_choice": evidence}, **options)


register_fitter("auto")(fit_best)
