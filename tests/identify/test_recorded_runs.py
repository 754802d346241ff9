"""Recorded runs as ``record`` writes them: command rows (no measurement) between the telemetry
rows. Start values, noise, autocorrelation and the initial state read the measured samples; and
a candidate's fit is never worse than the model without the effect."""

from __future__ import annotations

import numpy as np
import pytest

from mecanum_hil.identify.campaign import paper_campaign
from mecanum_hil.identify.diagnose import candidates
from mecanum_hil.identify.diagnose.heldout import in_sample_ms
from mecanum_hil.identify.diagnose.localise import _Evaluator, lag1_autocorrelation
from mecanum_hil.identify.fit import with_parameters
from mecanum_hil.identify.regimes import noise_sd, pooled_noise_sd
from mecanum_hil.link.effects_file import sim_effects_for
from mecanum_hil.model import Calibration, Effects, RobotProfile
from mecanum_hil.prediction import initial_wheel_rpm, predict
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
    # the braking limit's window is the rise time, timed from the command's own row when the
    # recording has it (without, from the next measured row): close, not equal
    got = candidates._start_values("braking_limit", with_rows, 0.25)
    assert got == pytest.approx(candidates._start_values("braking_limit", without, 0.25),
                                rel=0.1)
    # the steepest measured slope, not one diluted by rows read as zero: the 120 rpm step
    # rises at more than 1000 rpm/s (the first-order model's initial slope is A x 120)
    assert candidates._start_values("rate_limit", with_rows, 0.25)[
        "rate_limit_rpm_per_s"] > 1000.0
    assert candidates._start_values("saturation", with_rows, 0.25)[
        "top_speed_rpm"] == pytest.approx(1.02 * 110.0, abs=2.0)
    # the stop from the ceiling: the paper's loop brakes 110 rpm at more than 1000 rpm/s over
    # its rise time; read over that window, not over one noisy sample pair
    assert 1000.0 < candidates._start_values("braking_limit", with_rows, 0.25)[
        "braking_limit_rpm_per_s"] < 4000.0


def test_fit_start_values_read_the_measurements_not_the_command_rows(recorded):
    from mecanum_hil.identify.fit import _data_start_values, prepare

    rec = recorded[0]
    measured = rec.select(np.isfinite(rec.wheel_rpm).any(axis=1))
    got = _data_start_values(prepare([rec], ROBOT))
    assert got == pytest.approx(_data_start_values(prepare([measured], ROBOT)))
    assert got["rate_limit_rpm_per_s"] > 100.0


@pytest.mark.parametrize("effect", ["rate_limit", "breakaway", "braking_limit"])
def test_a_candidate_never_ends_worse_than_the_model_without_it(recorded, monkeypatch,
                                                                  effect):
    """The searches from the data's start values can end in a local minimum worse than the
    model without the effect (a kinked cost): then the candidate is searched from the model as
    it is, and is never worse than it."""
    ev = _Evaluator(recorded, ROBOT)
    base = with_parameters(Calibration(), {"top_speed_rpm": 110.0})
    harmful = {"rate_limit": {"rate_limit_rpm_per_s": 50.0},
               "breakaway": {"breakaway_rpm_per_s": 5000.0},
               "braking_limit": {"braking_limit_rpm_per_s": 30.0}}[effect]

    def stuck(ev, effect, base, cal, guess, bounds, base_free, free, sources, two_stage):
        return candidates._Fitted(effect, with_parameters(base, harmful), tuple(free), {}, ())

    monkeypatch.setattr(candidates, "_searched", stuck)
    f = candidates.fit_candidate(ev, effect, base, ["A", "B", "C", "top_speed_rpm"],
                                 ["step"], 0.25)
    assert in_sample_ms(ev, with_parameters(base, harmful)) > 2.0 * in_sample_ms(ev, base)
    assert in_sample_ms(ev, f.calibration) <= in_sample_ms(ev, base) * (1.0 + 1e-9)


def _measured(rec):
    return rec.select(np.isfinite(rec.wheel_rpm).any(axis=1))


def test_noise_and_autocorrelation_skip_the_command_rows(recorded):
    """A residual 30 x the noise (the model without the ceiling) is structured whatever rows
    lie between its samples; the noise level comes from all of them."""
    rec = recorded[0]
    wrong = Calibration()  # no ceiling: a large, smooth residual at 110 rpm
    res = rec.wheel_rpm - predict(rec, wrong, ROBOT).wheel_rpm
    only = _measured(rec)
    res_only = only.wheel_rpm - predict(only, wrong, ROBOT).wheel_rpm
    assert lag1_autocorrelation([res]) == pytest.approx(lag1_autocorrelation([res_only]),
                                                         abs=0.02)
    assert lag1_autocorrelation([res]) > 0.9
    truth = with_parameters(Calibration(), {"top_speed_rpm": 110.0})
    noise = rec.wheel_rpm - predict(rec, truth, ROBOT).wheel_rpm
    assert noise_sd(noise) == pooled_noise_sd([noise])
    assert noise_sd(noise) == pytest.approx(0.25, rel=0.15)


def test_a_recording_that_starts_on_a_command_row_in_motion(recorded):
    """Cut in mid-run at 110 rpm so that the first row is a command row: the model starts
    from the first reading, as it does when the first row is a reading."""
    rec = recorded[0]
    cmd_rows = np.flatnonzero(np.isnan(rec.wheel_rpm).all(axis=1) & (rec.t_s > 0.8))
    cut = rec.select(np.arange(len(rec)) >= cmd_rows[0])
    assert np.isnan(cut.wheel_rpm[0]).all()
    start = initial_wheel_rpm(cut)
    np.testing.assert_allclose(start, 110.0, atol=1.5)
    np.testing.assert_allclose(start, initial_wheel_rpm(_measured(cut)), atol=0.5)


def test_an_hour_long_pause_skips_the_reference_grid_instead_of_filling_it(recorded):
    """A recording with a pause of an hour between two samples: the uniform grids of the
    reference model and of the residual's spectrum would hold 360,000 points per hour (a
    MemoryError for a clock that jumps by years); they are skipped."""
    from mecanum_hil.identify.diagnose.localise import residual_shape
    from mecanum_hil.identify.diagnose.reference import fit_reference

    rec = recorded[0]
    t = rec.t_s.copy()
    t[len(t) // 2:] += 3600.0
    paused = rec.with_values(t_s=t)
    assert fit_reference([paused], ROBOT) is None
    assert fit_reference([rec], ROBOT) is not None
    res = paused.wheel_rpm - predict(paused, Calibration(), ROBOT).wheel_rpm
    shape = residual_shape([paused], [res], ROBOT)
    assert sum(shape.shares.values()) == pytest.approx(1.0)


def test_braking_limit_starts_at_the_data_scale_when_no_wheel_slows():
    """A recording in which no wheel is seen slowing (an overdamped rise) has no deceleration
    to read: the braking limit starts at the steepest measured slope, not at 1 rpm/s (which
    would bind on the model's first stop)."""
    from mecanum_hil.io.recording import Recording
    from mecanum_hil.model.simulate import simulate

    t = np.arange(501) / 100.0
    cmd = np.tile([0.0, 0.0, 90.0], (t.size, 1))
    cmd[10:, 0] = 60.0
    w = simulate(cmd, t, Calibration(A=20.0, B=2.0, C=5.0)).wheel_rpm[0]
    assert np.all(np.diff(w[:, 0]) >= 0)
    ev = _Evaluator([Recording(t, cmd, w, np.full((t.size, 3), np.nan))], ROBOT)
    got = candidates._start_values("braking_limit", ev, 0.2)["braking_limit_rpm_per_s"]
    assert got > 500.0  # the rise's scale: 60 rpm in the rise time
    # a rise to -80 rpm, with noise: the noise's and the settle's slopes towards rest are not
    # a deceleration (a second reading found the start at 4-300 rpm/s)
    cmd[10:, 0] = -80.0
    w = simulate(cmd, t, Calibration(A=20.0, B=2.0, C=5.0)).wheel_rpm[0]
    w = w + np.random.default_rng(1).normal(0.0, 2.0, w.shape)
    ev = _Evaluator([Recording(t, cmd, w, np.full((t.size, 3), np.nan))], ROBOT)
    assert candidates._start_values("braking_limit", ev, 2.0)[
        "braking_limit_rpm_per_s"] > 500.0


def _steps_recording(targets, hold_s: float = 1.0, rate_hz: float = 100.0):
    """Straight-ahead commands through ``targets`` [rpm], each held ``hold_s``, with the paper
    model's wheel speeds as the measurements."""
    from mecanum_hil.io.recording import Recording
    from mecanum_hil.model.simulate import simulate

    t = np.arange(int(len(targets) * hold_s * rate_hz)) / rate_hz
    cmd = np.tile([0.0, 0.0, 90.0], (t.size, 1))
    cmd[:, 0] = np.asarray(targets, dtype=float)[(t // hold_s).astype(int)]
    w = simulate(cmd, t, Calibration()).wheel_rpm[0]
    return Recording(t, cmd, w, np.full((t.size, 3), np.nan))


def test_braking_delay_on_the_recordings_own_commands():
    """How much later a braking limit makes the wheels slow down, on the recording's commands:
    nothing for a limit no slowdown reaches; the coast's own time for a limit far below the
    loop's deceleration (100 rpm at 100 rpm/s reaches 10 % after 0.9 s, the loop alone in a
    fraction of that); and a reversal brakes on the whole jump (120 -> -120 rpm: the loop
    brakes twice as hard as on a stop, so a limit the stop hardly feels delays it); and the
    falls of a ringing loop's overshoots, with no stop commanded."""
    paper = Calibration()
    stop = [_steps_recording([0.0, 100.0, 0.0])]
    assert candidates.braking_delay_s(stop, paper, ROBOT) == 0.0
    fast = with_parameters(paper, {"braking_limit_rpm_per_s": 1e5})
    assert candidates.braking_delay_s(stop, fast, ROBOT) == pytest.approx(0.0, abs=1e-9)
    slow = with_parameters(paper, {"braking_limit_rpm_per_s": 100.0})
    assert 0.7 < candidates.braking_delay_s(stop, slow, ROBOT) < 0.9
    limit = with_parameters(paper, {"braking_limit_rpm_per_s": 1500.0})
    on_stop = candidates.braking_delay_s([_steps_recording([0.0, 120.0, 0.0])], limit, ROBOT)
    on_reversal = candidates.braking_delay_s([_steps_recording([0.0, 120.0, -120.0])], limit,
                                             ROBOT)
    assert on_stop < 0.005 and on_reversal > 0.02
    # no stop at all: the overshoots' falls of a ringing loop (testPid7's, a single step)
    ringing = Calibration(A=3.8, B=3.0, C=1246.0)
    step = [_steps_recording([200.0, 200.0], rate_hz=500.0)]
    limited = with_parameters(ringing, {"braking_limit_rpm_per_s": 3149.0})
    assert candidates.braking_delay_s(step, limited, ROBOT) > 0.004


def test_a_braking_limit_within_two_samples_of_a_slowdown_is_not_resolved(recorded):
    """A limit that delays the model's slowdowns on the recordings by less than two sample
    periods (10 ms each here) is what a stop that starts a few ms late looks like (a loaded
    link's latency): the data cannot name it, and the candidate is the model without it. One
    that delays them by more stays."""
    ev = _Evaluator(recorded, ROBOT)
    base = with_parameters(Calibration(), {"top_speed_rpm": 110.0})
    free = ("A", "B", "C", "top_speed_rpm")

    def fitted(limit):
        return candidates._Fitted("braking_limit",
                                  with_parameters(base, {"braking_limit_rpm_per_s": limit}),
                                  (*free, "braking_limit_rpm_per_s"), {}, ())

    near = fitted(1200.0)
    assert 0.0 < candidates.braking_delay_s(ev.recs, near.calibration, ROBOT) < 0.02
    got = candidates._resolved(ev, near, base, free, 0.25)
    assert got.calibration is base and "cannot tell it from a stop that starts late" in got.absent
    far = fitted(300.0)
    assert candidates.braking_delay_s(ev.recs, far.calibration, ROBOT) > 0.02
    assert candidates._resolved(ev, far, base, free, 0.25) is far
