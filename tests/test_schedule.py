"""The converge schedule: learning rate and stop set by the held-out monitor, resumable, chosen by the recipe."""

import math
import sys

import pytest
import torch

from dynbtf.data.open import open_btf
from dynbtf.errors import DynBTFError
from dynbtf.representations.model_file import load_model
from dynbtf.training import TrainConfig, checkpoint_path, get_fitter
from dynbtf.training.fit import WRITE_RESERVE_SECONDS
from dynbtf.training.images import held_out_split
from dynbtf.training.recipe import REFERENCE_STEPS, auto_recipe
from dynbtf.training.schedule import ANNEAL_FLOOR, PlateauRule, Schedule

from interrupt import Stop, stop_at

pytestmark = pytest.mark.usefixtures("single_thread")


def test_plateau_rule_halves_at_each_stall_and_stops_at_the_lowest_rate():
    rule = PlateauRule(factor=0.5, patience=2, threshold_db=0.02, decays=2)
    improving = [20.0 + 0.1 * k for k in range(30)]
    assert rule.state(improving) == (0, False)  # never stalls
    # gains of 0.01 dB are no gains: a stall every 2 checks after the first
    flat = [20.0] * 7
    assert [rule.state(flat[:n]) for n in range(1, 8)] == [
        (0, False), (0, False), (1, False), (1, False), (2, False), (2, False), (2, True)]
    assert rule.state([20.0, 20.5, float("nan"), float("nan")]) == (1, False)  # NaN is no gain
    # the steady decay counts: at a rate already at the floor, the first stall stops
    assert rule.state([20.0, 20.0, 20.0], anneal=[1.0, 0.5, 0.25]) == (0, True)


def test_schedule_multiplier_is_the_halvings_times_a_steady_decay_to_the_floor_over_the_ceilings_last_third():
    schedule = Schedule("converge", epochs=9, steps_per_epoch=100, monitor_every=50, min_steps=0)
    assert schedule.anneal(0) == schedule.anneal(600) == 1.0 and math.isclose(schedule.anneal(900), 1 / 32)
    assert math.isclose(schedule.anneal(750), 2 ** -2.5) and schedule.anneal(5000) == schedule.anneal(900)
    record = [{"step": 50 * (k + 1), "held_out_psnr": 20.0} for k in range(3)]  # one stall after the best
    assert math.isclose(schedule.lr_multiplier(1, 150, record), 0.5 * schedule.anneal(150))
    assert schedule.monitor_due(50, False) and not schedule.monitor_due(60, True)
    paper = Schedule("epochs", epochs=10, steps_per_epoch=100, lr_decay=0.9)
    assert paper.lr_multiplier(3, 350, []) == 0.9 ** 3 and paper.monitor_due(300, True)
    assert not paper.converged(999, [{"step": 1, "held_out_psnr": 1.0}] * 50)


def _config(**options):
    return TrainConfig(**{"epochs": 3, "texel_groups": 4, "schedule": "converge", "monitor_every": 25,
                          "monitor_pairs": 4, "workers": 1, "device": "cpu", "precision": "fp32",
                          "lr_scale": 6.0, **options})


def test_a_converge_fit_stops_on_its_monitor_and_an_interrupted_one_ends_identically(tmp_path):
    source = open_btf("sim:leather?size=8")
    config = _config()
    whole = get_fitter("triple")(source, tmp_path / "whole.dbtfm", config, progress=False)
    provenance = whole.metadata["provenance"]
    record = provenance["schedule"]["monitor"]
    schedule = Schedule("converge", epochs=3, steps_per_epoch=390, monitor_every=25)
    assert provenance["schedule"]["stopped"] == "converged" and whole.finished
    steps = provenance["schedule"]["steps"]
    assert steps < 3 * 390 and steps == record[-1]["step"]
    rule = PlateauRule()
    halvings = [rule.state([r["held_out_psnr"] for r in record[:i]],
                           [schedule.anneal(r["step"]) for r in record[:i]])[0] for i in range(len(record))]
    assert halvings[-1] >= 1  # the rate was halved on the way
    for r, k in zip(record, halvings):  # the rate each check was trained at: the rule's, recomputed here
        assert math.isclose(r["lr_multiplier"], 0.5 ** k * schedule.anneal(r["step"] - 1), rel_tol=1e-12)

    with pytest.raises(Stop):
        get_fitter("triple")(source, tmp_path / "resumed.dbtfm", config, progress=False, callback=stop_at(137))
    assert checkpoint_path(tmp_path / "resumed.dbtfm").exists()
    resumed = get_fitter("triple")(source, tmp_path / "resumed.dbtfm", config, progress=False)
    assert resumed.metadata["provenance"]["schedule"] == provenance["schedule"] | {
        "monitor": resumed.metadata["provenance"]["schedule"]["monitor"]}
    assert [r["held_out_psnr"] for r in resumed.metadata["provenance"]["schedule"]["monitor"]] == \
        [r["held_out_psnr"] for r in record]
    a, _ = load_model(tmp_path / "whole.dbtfm")
    b, _ = load_model(tmp_path / "resumed.dbtfm")
    for name, tensor in a.state_dict().items():
        assert torch.equal(tensor, b.state_dict()[name]), name


def test_a_checkpoint_with_a_damaged_monitor_record_is_refused_by_name(tmp_path):
    source = open_btf("sim:leather?size=8")
    out = tmp_path / "m.dbtfm"
    with pytest.raises(Stop):
        get_fitter("triple")(source, out, _config(), progress=False, callback=stop_at(60))
    ckpt = checkpoint_path(out)
    state = torch.load(ckpt, weights_only=True)
    assert [r["step"] for r in state["monitor"]] == [25, 50]
    state["monitor"] = [{"step": "x"}]
    torch.save(state, ckpt)
    with pytest.raises(DynBTFError, match="damaged checkpoint: its monitor record"):
        get_fitter("triple")(source, out, _config(), progress=False)


def test_the_auto_recipe_trains_until_converged_under_a_ceiling_set_by_the_step_size():
    stone = auto_recipe(open_btf("sim:stone?size=128"))
    assert stone.config.schedule == "converge" and stone.config.epochs == 30  # 30 x 390 steps: the reference
    assert "until the held-out monitor stops improving" in stone.summary
    small = auto_recipe(open_btf("sim:stone?size=64&grid=ubo2014"))  # a quarter of the samples per step: 2x steps
    per_epoch = math.ceil(len(held_out_split(151, 151, 0.05, 0)[0]) / 16)
    assert small.config.schedule == "converge"
    assert small.config.epochs == math.ceil(2 * REFERENCE_STEPS / per_epoch - 0.05)
    # its checks and minimum scale with the steps: a check after as many samples as at 128 x 128
    assert (stone.config.monitor_every, stone.config.min_steps) == (390, 2922)
    assert (small.config.monitor_every, small.config.min_steps) == (780, 5844)
    assert auto_recipe(open_btf("sim:stone?size=64&grid=ubo2014"), monitor_every=100).config.monitor_every == 100
    fixed = auto_recipe(open_btf("sim:stone?size=128"), epochs=5)
    assert fixed.config.schedule == "epochs" and fixed.config.epochs == 5 and "5 epochs x 390 steps" in fixed.summary
    no_held_out = auto_recipe(open_btf("sim:stone?size=128"), held_out_fraction=0.0)
    assert no_held_out.config.schedule == "epochs"


def test_converge_without_held_out_pairs_is_refused():
    with pytest.raises(DynBTFError, match="needs held-out pairs"):
        get_fitter("triple")(open_btf("sim:leather?size=8"), "/tmp/never.dbtfm", _config(held_out_fraction=0.0),
                             progress=False)


def test_a_lowered_ceiling_moves_the_decay_and_the_end():
    schedule = Schedule("converge", epochs=9, steps_per_epoch=100, monitor_every=50, min_steps=0)
    record = [{"step": 50, "held_out_psnr": 20.0}, {"step": 100, "held_out_psnr": 21.0, "ceiling": 600},
              {"step": 150, "held_out_psnr": 22.0, "ceiling": 700}]  # a later, higher plan does not raise it
    assert schedule.ceilings(record) == [900, 600, 600] and schedule.ceiling(record) == 600
    assert schedule.ceiling([]) == 900
    # the decay over the last third of the lowered ceiling: from step 400 to x1/32 at 600
    assert schedule.lr_multiplier(0, 400, record) == 1.0
    assert math.isclose(schedule.lr_multiplier(0, 500, record), ANNEAL_FLOOR ** 0.5)
    assert math.isclose(schedule.lr_multiplier(0, 600, record), ANNEAL_FLOOR)
    assert schedule.replan(150, 300.7, record) == 450 and schedule.replan(150, 500, record) is None
    assert Schedule("epochs", epochs=9, steps_per_epoch=100).replan(150, 10, record) is None


class _Clock:
    """A stand-in for the ``time`` module in :mod:`dynbtf.training.fit`: ``seconds_per_step(step)`` pass when a
    step ends (and a nanosecond per reading), so the budget's arithmetic holds whatever the machine's speed."""

    def __init__(self, seconds_per_step):
        self.now, self.seconds_per_step = 1000.0, seconds_per_step

    def perf_counter(self):
        self.now += 1e-9
        return self.now

    def callback(self, info):
        self.now += self.seconds_per_step(info["global_step"])


def test_a_budget_fit_the_machine_slows_down_ends_annealed_at_the_ceiling_it_replans(tmp_path, monkeypatch):
    """1 s per step, then 3 s from step 100 on, under a 10-minute budget: each check after the first re-plans the
    ceiling to what 95 % of the budget's rest affords at the last interval's rate; the fit ends there, its rate
    decayed to the floor, inside the budget (cut by the budget mid-schedule, it would end at the unannealed rate)."""
    clock = _Clock(lambda step: 1.0 if step <= 100 else 3.0)
    monkeypatch.setattr(sys.modules["dynbtf.training.fit"], "time", clock)
    result = get_fitter("triple")(open_btf("sim:leather?size=8"), tmp_path / "m.dbtfm", _config(max_minutes=10.0),
                                  progress=False, callback=clock.callback)
    schedule_info = result.metadata["provenance"]["schedule"]
    record, steps = schedule_info["monitor"], schedule_info["steps"]
    assert result.finished and schedule_info["stopped"] == "ceiling"
    # the plans, recomputed (the check of step k sees steps 1..k-1 on the clock); the first check (25) starts the
    # clock, with the second kept for writing the model after the last step); at 50, 25 steps in 25 s
    plans = {r["step"]: r["ceiling"] for r in record if "ceiling" in r}
    end = 600 - WRITE_RESERVE_SECONDS
    assert 25 not in plans and abs(plans[50] - (50 + 0.95 * (end - 49))) <= 1
    # at 125 (100 + 24 x 3 s spent): 25 steps in 73 s since the plan at 100
    assert abs(plans[125] - (125 + 0.95 * (end - 172) * 25 / 73)) <= 1
    assert steps == min(plans.values()) < 3 * 390
    assert clock.now - 1000.0 <= 600.0  # inside the budget
    schedule = Schedule("converge", epochs=3, steps_per_epoch=390, monitor_every=25)
    assert math.isclose(schedule.anneal(steps, steps), ANNEAL_FLOOR)
