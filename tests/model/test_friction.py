"""The ``friction`` effect: a Coulomb friction on the turning wheel. Against a fine Euler
reference of the same equations, the offset it leaves a proportional loop, its steady state,
and the calibration file."""

from __future__ import annotations

import numpy as np
import pytest
from euler_reference import pi_loop_euler

from mecanum_hil.errors import ConfigError
from mecanum_hil.model import Calibration, Effects
from mecanum_hil.model.calibration import load_calibration, save_calibration
from mecanum_hil.model.simulate import simulate, steady_state, uniform_time

T = uniform_time(3.0, 100)
LEVELS = ((0.1, 150.0), (1.0, 40.0), (1.8, -120.0), (2.5, 0.0))


def _targets(t: np.ndarray) -> np.ndarray:
    u = np.zeros_like(t)
    for start, level in LEVELS:
        u[t >= start] = level
    return u


def _commands() -> np.ndarray:
    cmd = np.zeros((T.size, 3))
    cmd[:, 0] = _targets(T)
    cmd[:, 2] = 90.0
    return cmd


def _wheel(A: float, B: float, C: float, effects: Effects) -> np.ndarray:
    return simulate(_commands(), T, Calibration(A, B, C, effects=effects)).wheel_rpm[0, :, 0]


@pytest.mark.parametrize("A, B, C, fric", [(14.7, 16.1, 303.0, 800.0),
                                           (40.0, 5.0, 1e-3, 600.0),
                                           (300.0, 10.0, 2000.0, 3000.0)])
def test_friction_follows_the_euler_reference(A, B, C, fric):
    got = _wheel(A, B, C, Effects(friction_rpm_per_s=fric))
    assert np.abs(got - pi_loop_euler(A, B, C, T, _targets, fric)).max() < 0.5


def test_a_proportional_loop_settles_short_by_an_offset_that_does_not_scale():
    A, B, C, fric = 40.0, 5.0, 1e-3, 600.0
    got = _wheel(A, B, C, Effects(friction_rpm_per_s=fric))
    at = {level: got[np.searchsorted(T, start + 0.6)] for start, level in LEVELS[:3]}
    for level, y in at.items():  # (A u - F sign(u)) / (A + B)
        assert y == pytest.approx((A * level - np.sign(level) * fric) / (A + B), abs=0.05)
    assert got[-1] == 0.0  # stopped and held by the friction


def test_a_pi_loop_reaches_its_target_later_with_friction():
    A, B, C = 14.7, 16.1, 303.0
    free = _wheel(A, B, C, Effects())
    rubbing = _wheel(A, B, C, Effects(friction_rpm_per_s=800.0))
    first = (T >= 0.1) & (T < 1.0)
    assert rubbing[first].max() < free[first].max()
    assert rubbing[np.searchsorted(T, 0.95)] == pytest.approx(150.0, abs=0.5)


def test_friction_on_the_drive_dynamics_paths_offsets_a_proportional_loop():
    A, B, C, fric = 40.0, 5.0, 1e-3, 600.0
    for extra in ({"controller_period_s": 0.004}, {"drive_lag_s": 0.005},
                  {"breakaway_rpm_per_s": 900.0}):
        got = _wheel(A, B, C, Effects(friction_rpm_per_s=fric, **extra))
        y = got[np.searchsorted(T, 0.7)]
        assert y == pytest.approx((A * 150.0 - fric) / (A + B), abs=0.5), extra


def test_a_recording_started_in_steady_state_stays_there_with_friction():
    cal = Calibration(40.0, 5.0, 2.0, effects=Effects(friction_rpm_per_s=600.0))
    state = steady_state(cal, [120.0] * 4, [120.0] * 4)
    cmd = np.tile([120.0, 0.0, 90.0], (T.size, 1))
    w = simulate(cmd, T, cal, initial_state=state).wheel_rpm[0, :, 0]
    assert np.abs(w - 120.0).max() < 1e-6


def test_friction_round_trips_through_the_calibration_file(tmp_path):
    cal = Calibration(20.0, 15.0, 400.0, effects=Effects(friction_rpm_per_s=412.5,
                                                          dead_time_s=0.01))
    back = load_calibration(save_calibration(cal, tmp_path / "f.toml"))
    assert back.effects == cal.effects
    assert "[effects.friction]" in (tmp_path / "f.toml").read_text()


def test_friction_is_not_in_one_model_with_a_coasting_drive(tmp_path):
    with pytest.raises(ConfigError, match="friction is not used together"):
        Effects(friction_rpm_per_s=300.0, braking_limit_rpm_per_s=900.0)
    with pytest.raises(ConfigError, match="friction is not used together"):
        Effects(friction_rpm_per_s=300.0, coast_decel_rpm_per_s=900.0)
    path = tmp_path / "both.toml"
    path.write_text("[motor]\nA = 20.0\nB = 15.0\nC = 400.0\n[effects.friction]\n"
                    "friction_rpm_per_s = 300.0\n[effects.fast_decay]\n"
                    "coast_decel_rpm_per_s = 900.0\n")
    with pytest.raises(ConfigError, match=r"both\.toml.*friction is not used together"):
        load_calibration(path)
    with pytest.raises(ConfigError, match="friction_rpm_per_s must be finite"):
        Effects(friction_rpm_per_s=-1.0)
