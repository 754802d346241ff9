"""The drive's own dynamics in the simulator: controller period, drive lag, breakaway."""

from __future__ import annotations

import numpy as np
import pytest

from mecanum_hil.model import Calibration, Effects
from mecanum_hil.model.calibration import exchange_drive_lag, load_calibration, save_calibration
from mecanum_hil.model.simulate import simulate, uniform_time

T = uniform_time(1.5, 500)


def _commands(n_rpm=60.0, reverse_at=None):
    cmd = np.zeros((T.size, 3))
    cmd[:, 2] = 90.0
    cmd[5:, 0] = n_rpm
    if reverse_at is not None:
        cmd[reverse_at:, 0] = -n_rpm
    return cmd


def _wheel(effects: Effects, **kw) -> np.ndarray:
    return simulate(_commands(**kw), T, Calibration(effects=effects)).wheel_rpm[0, :, 0]


def test_tiny_effects_approach_the_paper_model():
    ref = _wheel(Effects())
    assert np.abs(_wheel(Effects(breakaway_rpm_per_s=1e-9)) - ref).max() < 1e-9
    assert np.abs(_wheel(Effects(drive_lag_s=1e-5)) - ref).max() < 0.1
    assert np.abs(_wheel(Effects(controller_period_s=1e-4)) - ref).max() < 0.1


def test_breakaway_holds_the_wheel_until_the_drive_exceeds_it():
    # the paper's PI: drive at rest = A u + C u t; with 60 rpm it reaches 3000 rpm/s after
    # (3000 - 14.7 * 60) / (303 * 60) = 0.117 s
    w = _wheel(Effects(breakaway_rpm_per_s=3000.0))
    t_go = (3000.0 - 14.7 * 60.0) / (303.0 * 60.0)
    step = T[5]
    assert np.all(w[T <= step + t_go - 0.003] == 0.0)
    assert w[np.searchsorted(T, step + t_go + 0.01)] > 0.5
    # the integrator wound up meanwhile: a larger overshoot than without
    assert w.max() > _wheel(Effects()).max() + 5.0
    assert w[-1] == pytest.approx(60.0, abs=0.5)


def test_breakaway_sticks_a_wheel_that_stops_on_a_reversal():
    w = _wheel(Effects(breakaway_rpm_per_s=3000.0), reverse_at=400)
    stuck = np.flatnonzero(w[400:] == 0.0)
    assert stuck.size > 5  # at rest for a while before the drive breaks it away backwards
    assert w[-1] < -50.0


def test_drive_lag_makes_the_loop_ring_more():
    base, lag = _wheel(Effects()), _wheel(Effects(drive_lag_s=0.03))
    assert lag.max() > base.max() + 3.0
    assert lag[-1] == pytest.approx(60.0, abs=0.5)


def test_controller_period_holds_the_output():
    w = _wheel(Effects(controller_period_s=0.02))
    # the output held over a period acts on old speeds: a visibly different response
    assert np.abs(w - _wheel(Effects())).max() > 1.0
    # the time to the controller's next tick travels in the state (column 20)
    traj = simulate(_commands()[:101], T[:101], Calibration(effects=Effects(
        controller_period_s=0.02)))
    # 0.2 s is ten whole periods: the next tick is due now
    assert traj.final_state[0, 20] == pytest.approx(0.0, abs=1e-9)
    assert w[-1] == pytest.approx(60.0, abs=0.5)


@pytest.mark.parametrize("effects", [
    Effects(controller_period_s=0.012), Effects(drive_lag_s=0.02),
    Effects(breakaway_rpm_per_s=2500.0),
    Effects(controller_period_s=0.005, drive_lag_s=0.01, breakaway_rpm_per_s=1500.0,
            top_speed_rpm=70.0, rate_limit_rpm_per_s=800.0),
])
def test_a_simulation_continues_exactly_from_its_final_state(effects):
    cal = Calibration(effects=effects)
    cmd = _commands(reverse_at=450)
    whole = simulate(cmd, T, cal)
    k = 333
    a = simulate(cmd[:k + 1], T[:k + 1], cal)
    b = simulate(cmd[k:], T[k:], cal, initial_state=a.final_state, initial_pose=a.pose[0, -1])
    np.testing.assert_allclose(b.wheel_rpm[0], whole.wheel_rpm[0, k:], atol=1e-9)
    np.testing.assert_allclose(b.pose[0], whole.pose[0, k:], atol=1e-9)


def test_a_wheels_only_state_is_accepted():
    a = simulate(_commands(), T, Calibration())
    b = simulate(_commands(), T, Calibration(), initial_state=a.final_state[:, :12])
    assert b.final_state.shape == (1, 21)


def test_new_effects_round_trip_through_a_calibration_file(tmp_path):
    eff = Effects(controller_period_s=0.004, drive_lag_s=0.015, breakaway_rpm_per_s=2200.0)
    path = save_calibration(Calibration(effects=eff), tmp_path / "c.toml")
    text = path.read_text()
    for name in ("controller_period", "drive_lag", "breakaway"):
        assert f"[effects.{name}]" in text
    assert load_calibration(path).effects == eff


@pytest.mark.parametrize("effects", [
    Effects(drive_lag_s=0.12),
    Effects(drive_lag_s=0.03, top_speed_rpm=50.0, dead_time_s=0.02, gains=(1.0, 0.9, 1.1, 1.0),
            rate_limit_rpm_per_s=400.0, deadband_rpm=2.0, controller_period_s=0.006),
])
def test_drive_lag_and_motor_pole_are_interchangeable(effects):
    # the lag's twin (lag <-> 1 / B, A and C rescaled) gives the same wheel speeds exactly:
    # wheel speeds alone cannot tell which time constant is the drive's and which the motor's
    cal = Calibration(effects=effects)
    twin = exchange_drive_lag(cal)
    assert twin.effects.drive_lag_s == pytest.approx(1.0 / cal.B)
    assert twin.B == pytest.approx(1.0 / effects.drive_lag_s)
    cmd = _commands(reverse_at=400)
    a = simulate(cmd, T, cal).wheel_rpm[0]
    b = simulate(cmd, T, twin).wheel_rpm[0]
    assert np.abs(a - b).max() < 1e-6 * np.abs(a).max()
    assert exchange_drive_lag(twin).effects.drive_lag_s == pytest.approx(effects.drive_lag_s)


def test_breakaway_tells_the_lag_from_the_motor_pole():
    fx = Effects(drive_lag_s=0.03, breakaway_rpm_per_s=1500.0)
    assert exchange_drive_lag(Calibration(effects=fx)) is None
