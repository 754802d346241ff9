"""Start values read off recorded runs (diagnose's candidates, fit's effects), and a candidate's
fit never worse than the model without the effect."""

from __future__ import annotations

import numpy as np
import pytest

from mecanum_hil.identify.campaign import paper_campaign
from mecanum_hil.identify.diagnose import candidates
from mecanum_hil.identify.diagnose.heldout import in_sample_ms
from mecanum_hil.identify.diagnose.localise import _Evaluator
from mecanum_hil.identify.fit import with_parameters
from mecanum_hil.link.effects_file import sim_effects_for
from mecanum_hil.model import Calibration, Effects, RobotProfile
from mecanum_hil.profiles import step

ROBOT = RobotProfile()


@pytest.fixture(scope="module")
def recorded():
    """A recorded run as ``record`` writes it: the command rows (50 Hz) carry no measurement
    between the telemetry rows (100 Hz); a 120 rpm step into a 110 rpm ceiling."""
    hidden = sim_effects_for(Effects(top_speed_rpm=110.0), wheel_rpm_std=0.25, seed=3)
    recs = paper_campaign(hidden, ROBOT, seed=3, pose_noise=None,
                          profiles=[step(120.0, duration_s=1.5, rest_s=0.3, stop_s=1.0)])
    assert np.isnan(recs[0].wheel_rpm).all(axis=1).any()  # command rows are there
    return recs


def test_start_values_read_the_measurements_not_the_command_rows(recorded):
    rec = recorded[0]
    measured = rec.select(np.isfinite(rec.wheel_rpm).any(axis=1))
    with_rows, without = _Evaluator([rec], ROBOT), _Evaluator([measured], ROBOT)
    assert candidates._sample_period_s(with_rows) == pytest.approx(0.01, rel=0.05)
    assert candidates._sample_period_s(with_rows) == candidates._sample_period_s(without)
    assert rec.measured_period_s == measured.measured_period_s
    for effect in ("rate_limit", "saturation"):
        got = candidates._start_values(effect, with_rows, 0.25)
        assert got == pytest.approx(candidates._start_values(effect, without, 0.25)), effect
    # the steepest measured slope, not one diluted by rows read as zero: the 120 rpm step
    # rises at more than 1000 rpm/s (the first-order model's initial slope is A x 120)
    assert candidates._start_values("rate_limit", with_rows, 0.25)[
        "rate_limit_rpm_per_s"] > 1000.0
    assert candidates._start_values("saturation", with_rows, 0.25)[
        "top_speed_rpm"] == pytest.approx(1.02 * 110.0, abs=2.0)


def test_fit_start_values_read_the_measurements_not_the_command_rows(recorded):
    from mecanum_hil.identify.fit import _data_start_values, prepare

    rec = recorded[0]
    measured = rec.select(np.isfinite(rec.wheel_rpm).any(axis=1))
    got = _data_start_values(prepare([rec], ROBOT))
    assert got == pytest.approx(_data_start_values(prepare([measured], ROBOT)))
    assert got["rate_limit_rpm_per_s"] > 100.0


@pytest.mark.parametrize("effect", ["rate_limit", "breakaway"])
def test_a_candidate_never_ends_worse_than_the_model_without_it(recorded, monkeypatch,
                                                                  effect):
    """The searches from the data's start values can end in a local minimum worse than the
    model without the effect (a kinked cost): then the candidate is searched from the model as
    it is, and is never worse than it."""
    ev = _Evaluator(recorded, ROBOT)
    base = with_parameters(Calibration(), {"top_speed_rpm": 110.0})
    harmful = {"rate_limit": {"rate_limit_rpm_per_s": 50.0},
               "breakaway": {"breakaway_rpm_per_s": 5000.0}}[effect]

    def stuck(ev, effect, base, cal, guess, bounds, base_free, free, sources, two_stage):
        return candidates._Fitted(effect, with_parameters(base, harmful), tuple(free), {}, ())

    monkeypatch.setattr(candidates, "_searched", stuck)
    f = candidates.fit_candidate(ev, effect, base, ["A", "B", "C", "top_speed_rpm"],
                                 ["step"], 0.25)
    assert in_sample_ms(ev, with_parameters(base, harmful)) > 2.0 * in_sample_ms(ev, base)
    assert in_sample_ms(ev, f.calibration) <= in_sample_ms(ev, base) * (1.0 + 1e-9)
