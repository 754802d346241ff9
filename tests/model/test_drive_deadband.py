"""The ``drive_deadband`` effect: a firmware that switches its drive off for small targets, so
the wheel coasts instead of being braked to rest. Against a fine Euler reference, against the
target ``deadband``, and in the calibration file."""

from __future__ import annotations

import numpy as np
import pytest
from euler_reference import pi_loop_euler

from mecanum_hil.errors import ConfigError
from mecanum_hil.model import Calibration, Effects
from mecanum_hil.model.calibration import load_calibration, save_calibration
from mecanum_hil.model.simulate import simulate, uniform_time

T = uniform_time(4.0, 500)
#: (start [s], target [rpm]): into the deadband from both signs, and out of it
LEVELS = ((0.1, 150.0), (1.0, 20.0), (1.6, -120.0), (2.4, -10.0), (3.2, 60.0))
DEADBAND = 30.0


def _targets(t: np.ndarray) -> np.ndarray:
    u = np.zeros_like(t)
    for start, level in LEVELS:
        u[t >= start] = level
    return u


def _wheel(A: float, B: float, C: float, effects: Effects) -> np.ndarray:
    cmd = np.zeros((T.size, 3))
    cmd[:, 0] = _targets(T)
    cmd[:, 2] = 90.0
    return simulate(cmd, T, Calibration(A, B, C, effects=effects)).wheel_rpm[0, :, 0]


@pytest.mark.parametrize("A, B, C, fric", [(40.0, 2.0, 1e-3, 300.0),
                                           (14.7, 16.1, 303.0, 0.0),
                                           (14.7, 16.1, 303.0, 500.0)])
def test_drive_deadband_follows_the_euler_reference(A, B, C, fric):
    got = _wheel(A, B, C, Effects(drive_deadband_rpm=DEADBAND, friction_rpm_per_s=fric))
    assert np.abs(got - pi_loop_euler(A, B, C, T, _targets, fric, DEADBAND)).max() < 0.05


def test_a_wheel_whose_drive_is_off_coasts_where_a_deadband_brakes():
    A, B, C = 14.7, 4.0, 303.0  # a free-running wheel: its own pole is slow
    coast = _wheel(A, B, C, Effects(drive_deadband_rpm=DEADBAND))
    brake = _wheel(A, B, C, Effects(deadband_rpm=DEADBAND))
    stop = (T >= 1.0) & (T < 1.6)  # 150 rpm -> a target of 20 rpm, inside both deadbands
    half = 75.0
    t_coast = T[stop][np.argmax(coast[stop] < half)] - 1.0
    t_brake = T[stop][np.argmax(brake[stop] < half)] - 1.0
    assert t_coast == pytest.approx(np.log(2.0) / B, abs=0.01)  # the pole alone
    assert t_brake < 0.5 * t_coast
    # out of the deadband the loop takes over again from where the wheel is
    assert coast[np.searchsorted(T, 3.9)] == pytest.approx(60.0, abs=0.5)


def test_drive_deadband_round_trips_through_the_calibration_file(tmp_path):
    cal = Calibration(20.0, 15.0, 400.0, effects=Effects(drive_deadband_rpm=28.6,
                                                          friction_rpm_per_s=150.0))
    back = load_calibration(save_calibration(cal, tmp_path / "d.toml"))
    assert back.effects == cal.effects
    assert "[effects.drive_deadband]" in (tmp_path / "d.toml").read_text()


def test_drive_deadband_is_not_in_one_model_with_a_deadband_or_a_braking_limit():
    with pytest.raises(ConfigError, match="drive_deadband is not used together"):
        Effects(drive_deadband_rpm=20.0, deadband_rpm=5.0)
    with pytest.raises(ConfigError, match="drive_deadband is not used together"):
        Effects(drive_deadband_rpm=20.0, braking_limit_rpm_per_s=900.0)
    with pytest.raises(ConfigError, match="drive_deadband_rpm must be finite"):
        Effects(drive_deadband_rpm=float("inf"))
