"""``--repr auto``: the representation chosen by a trial of each kind on the same held-out pairs."""

import pytest
import torch

from dynbtf.cli.main import main
from dynbtf.data.open import open_btf
from dynbtf.representations.model_file import load_model, read_model_metadata
from dynbtf.training import TrainConfig, get_fitter
from dynbtf.training import model_choice
from dynbtf.training.model_choice import CANDIDATES, DECISIVE_RELIEF, MARGIN_DB, TRUSTED_RELIEF, fit_best, pick

pytestmark = pytest.mark.usefixtures("single_thread")


def test_pick_prefers_the_cheaper_kind_unless_beaten_by_the_margin():
    assert pick({"triple": 20.0, "triple-parallax": 20.0 + MARGIN_DB / 2}) == "triple"
    assert pick({"triple": 20.0, "triple-parallax": 20.0 + 2 * MARGIN_DB}) == "triple-parallax"
    assert pick({"triple": 22.0, "triple-parallax": 21.0}) == "triple"
    assert pick({"triple": float("nan"), "triple-parallax": 18.0}) == "triple-parallax"
    assert pick({"triple": 18.0, "triple-parallax": float("nan")}) == "triple"
    # measured trials: the lacquered wood (flat, glossy; parallax ends 2 dB behind) and a 64 x 64 stone (relief)
    assert pick({"triple": 26.60, "triple-parallax": 26.80}) == "triple"
    assert pick({"triple": 23.69, "triple-parallax": 28.12}) == "triple-parallax"
    # an undecided trial goes to the parallax model where the stereo height was trusted: leather, not the wood
    leather, wood = {"triple": 26.86, "triple-parallax": 26.82}, {"triple": 26.71, "triple-parallax": 26.81}
    assert pick(leather) == pick(wood) == "triple"
    assert pick(leather, stereo_trusted=TRUSTED_RELIEF) == "triple-parallax"
    assert pick(wood, stereo_trusted=TRUSTED_RELIEF / 2) == "triple"
    # the three undecided trials measured at 128 x 128, with their trusted fractions: the leather's relief wins
    # (the parallax model ends 4.6 dB ahead), the flat glossy ceramic tiles and lacquered wood stay flat (1.7 and 2 dB)
    ceramic = {"triple": 20.68, "triple-parallax": 20.22}
    assert (pick(leather, 0.45), pick(ceramic, 0.28), pick(wood, 0.002)) == ("triple-parallax", "triple", "triple")
    # a decided trial stays decided, and a parallax trial behind by more than the margin loses whatever the stereo
    assert pick({"triple": 23.69, "triple-parallax": 28.12}, stereo_trusted=0.0) == "triple-parallax"
    assert pick({"triple": 27.0, "triple-parallax": 27.0 - 2 * MARGIN_DB}, stereo_trusted=1.0) == "triple"
    assert pick({"triple": 27.0, "triple-parallax": float("nan")}, stereo_trusted=1.0) == "triple"
    # the stereo decides alone above the materials that ended better flat (tiles 0.28, wood 0.002) and at or below
    # those with a relief whose trials were decided (woven 0.71, brick 0.84, stone 0.86 and 0.88); the leather
    # (0.45), undecided at the trial, is left to the race
    assert max(0.28, 0.002, 0.45) < DECISIVE_RELIEF <= min(0.71, 0.84, 0.86, 0.88)


def _config(**options):
    return TrainConfig(**{"epochs": 2, "texel_groups": 4, "schedule": "converge", "monitor_every": 20,
                          "monitor_pairs": 4, "workers": 1, "device": "cpu", "precision": "fp32", "lr_scale": 6.0,
                          **options})


def test_the_race_continues_the_winner_to_the_same_model_as_its_own_fit(tmp_path, capsys, monkeypatch):
    source = open_btf("sim:stone?size=8")
    monkeypatch.setattr(model_choice, "DECISIVE_RELIEF", 1.01)  # the race, whatever the stereo finds
    result = fit_best(source, tmp_path / "auto.dbtfm", _config(), progress=True)
    printed = capsys.readouterr().out
    choice = result.metadata["provenance"]["representation_choice"]
    scores = {k: t["held_out_psnr"] for k, t in choice["trials"].items()}
    assert list(scores) == list(CANDIDATES) and all(t["steps"] == 60 for t in choice["trials"].values())
    assert all(0 < t["seconds_per_step"] for t in choice["trials"].values())  # of the steps run in that call
    trusted = choice["trials"]["triple-parallax"]["stereo_trusted"]
    assert 0.0 <= trusted <= 1.0 and choice["kind"] == pick(scores, trusted) == result.metadata["kind"]
    line = next(x for x in printed.splitlines() if x.startswith("representation: "))
    assert line.startswith(f"representation: {choice['kind']} (held-out PSNR after a trial of triple ")
    assert f"triple-parallax {scores['triple-parallax']:.2f} dB at step 60" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["auto.dbtfm"]  # no trial or checkpoint left
    direct = get_fitter(choice["kind"])(source, tmp_path / "direct.dbtfm", _config(), progress=False)
    a, _ = load_model(tmp_path / "auto.dbtfm")
    b, _ = load_model(direct.model_path)
    for name, tensor in a.state_dict().items():  # the trial was the first part of the winner's own fit
        assert torch.equal(tensor, b.state_dict()[name]), name
    # the trial's score is the direct fit's own check at the trial's end
    check = direct.metadata["provenance"]["schedule"]["monitor"][2]
    assert check["step"] == 60 and check["held_out_psnr"] == scores[choice["kind"]]
    again = fit_best(source, tmp_path / "auto.dbtfm", _config(), progress=True)  # a rerun: nothing to race
    assert "continuing" in capsys.readouterr().out and again.metadata["kind"] == choice["kind"]


def _fake_clock(monkeypatch, seconds_per_reading: float):
    """Every time.perf_counter() of the fit and the race advances a shared clock by ``seconds_per_reading``."""
    import importlib
    import itertools
    import types

    clock = itertools.count(0.0, seconds_per_reading)
    fake = types.SimpleNamespace(perf_counter=lambda: next(clock))
    for module in (importlib.import_module("dynbtf.training.fit"), model_choice):
        monkeypatch.setattr(module, "time", fake)


def test_a_budget_that_ends_in_the_race_writes_the_leader(tmp_path, capsys, monkeypatch):
    """The budget runs out during the first trial: the output is still a model (that trial's), the choice and why
    are one line, and the same call again continues its fit."""
    source = open_btf("sim:stone?size=8")
    monkeypatch.setattr(model_choice, "DECISIVE_RELIEF", 1.01)
    with monkeypatch.context() as patch:
        _fake_clock(patch, 10.0)  # 30 s of budget: a few readings
        stopped = fit_best(source, tmp_path / "auto.dbtfm", _config(max_minutes=0.5), progress=True)
    printed = capsys.readouterr().out
    line = next(x for x in printed.splitlines() if x.startswith("representation: "))
    assert line.startswith("representation: triple (") and "time budget" in line
    assert not stopped.finished and stopped.model_path.is_file()
    meta = read_model_metadata(tmp_path / "auto.dbtfm")
    assert meta["kind"] == "triple" and meta["provenance"]["representation_choice"]["race_finished"] is False
    assert (tmp_path / "auto.dbtfm.ckpt").exists()  # a later run continues the leader's fit
    again = fit_best(source, tmp_path / "auto.dbtfm", _config(), progress=True)
    assert "continuing" in capsys.readouterr().out and again.finished and again.metadata["kind"] == "triple"


def test_a_short_budget_sizes_both_trials_alike(tmp_path, capsys, monkeypatch):
    """A budget too short for the full trials: the first trial's step time sizes both to the same step count."""
    source = open_btf("sim:stone?size=8")
    monkeypatch.setattr(model_choice, "DECISIVE_RELIEF", 1.01)
    monkeypatch.setattr(model_choice, "MIN_TRIAL_STEPS", 5)
    with monkeypatch.context() as patch:
        _fake_clock(patch, 0.05)
        result = fit_best(source, tmp_path / "auto.dbtfm", _config(max_minutes=2.0, monitor_every=100),
                          progress=True)
    printed = capsys.readouterr().out
    choice = result.metadata["provenance"]["representation_choice"]
    steps = {k: t["steps"] for k, t in choice["trials"].items()}
    assert list(steps) == list(CANDIDATES) and len(set(steps.values())) == 1
    assert model_choice.MIN_TRIAL_STEPS <= steps["triple"] < 300  # fewer than 3 checks of 100 steps
    assert f"trial of triple: {steps['triple']} steps (sized to the time budget" in printed
    assert result.model_path.is_file() and choice["kind"] == result.metadata["kind"]


def test_a_relief_the_stereo_trusts_decides_without_a_trial(tmp_path, capsys, monkeypatch):
    from dynbtf.training.fitters import FITTERS, parallax_stereo_options
    from dynbtf.training.stereo_height import stereo_height

    source = open_btf("sim:stone?size=16")
    trusted = float(stereo_height(source, return_trusted=True, **parallax_stereo_options(source))[1].double().mean())
    assert trusted > 0.5  # a stone: a relief the views agree on

    class TrialStarted(Exception):
        pass

    def no_trial(*args, **kwargs):
        raise TrialStarted

    monkeypatch.setitem(FITTERS, "triple", no_trial)
    monkeypatch.setattr(model_choice, "DECISIVE_RELIEF", trusted + 1e-9)  # just below the threshold: the race
    with pytest.raises(TrialStarted):
        fit_best(source, tmp_path / "raced.dbtfm", _config(), progress=False)
    monkeypatch.setattr(model_choice, "DECISIVE_RELIEF", trusted)  # at the threshold: no trial of either kind
    result = fit_best(source, tmp_path / "auto.dbtfm", _config(), progress=True)
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("representation: "))
    assert line.startswith(f"representation: triple-parallax (stereo height trusted on {trusted:.0%} of the texels; "
                           f"triple-parallax without a trial where")
    choice = result.metadata["provenance"]["representation_choice"]
    assert choice["kind"] == result.metadata["kind"] == "triple-parallax"
    assert choice["stereo_trusted"] == trusted and choice["trials"] == {}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["auto.dbtfm"]
    direct = get_fitter("triple-parallax")(source, tmp_path / "direct.dbtfm", _config(), progress=False)
    a, _ = load_model(tmp_path / "auto.dbtfm")
    b, _ = load_model(direct.model_path)
    for name, tensor in a.state_dict().items():  # the model --repr triple-parallax trains, bit for bit
        assert torch.equal(tensor, b.state_dict()[name]), name


def test_auto_is_the_command_line_default_and_its_choice_is_in_the_model(tmp_path, capsys):
    out = tmp_path / "m.dbtfm"
    assert main(["fit", "sim:leather?size=8", "-o", str(out), "--epochs", "1", "--texel-groups", "4",
                 "--device", "cpu", "--workers", "1"]) == 0
    printed = capsys.readouterr().out
    assert "representation: " in printed
    meta = read_model_metadata(out)
    assert meta["kind"] in CANDIDATES and meta["provenance"]["representation_choice"]["kind"] == meta["kind"]
    assert main(["fit", "sim:leather?size=8", "-o", str(tmp_path / "x.dbtfm"), "--held-out-fraction", "0"]) == 2
    assert "--repr auto chooses by held-out PSNR" in capsys.readouterr().err
