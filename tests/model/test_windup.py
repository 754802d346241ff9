"""The ``windup`` effect: a drive output clamped without anti-windup. Against a fine Euler
reference of the same equations, against ``saturation`` (the clamp with anti-windup), and in
the calibration file."""

from __future__ import annotations

import numpy as np
import pytest

from mecanum_hil.errors import ConfigError
from mecanum_hil.model import Calibration, Effects
from mecanum_hil.model.calibration import load_calibration, save_calibration
from mecanum_hil.model.simulate import simulate, steady_state, uniform_time

A, B, C = 20.0, 15.0, 400.0
T = uniform_time(3.0, 500)
TOP = 350.0


def _commands(n_rpm: float = 300.0, reverse_at_s: float | None = None) -> np.ndarray:
    cmd = np.zeros((T.size, 3))
    cmd[:, 2] = 90.0
    cmd[T >= 0.1, 0] = n_rpm
    if reverse_at_s is not None:
        cmd[T >= reverse_at_s, 0] = -n_rpm
    return cmd


def _wheel(effects: Effects, **kw) -> np.ndarray:
    cal = Calibration(A, B, C, effects=effects)
    return simulate(_commands(**kw), T, cal).wheel_rpm[0, :, 0]


def _euler(n_rpm: float, windup: bool, reverse_at_s: float | None = None,
           dt: float = 2e-6) -> np.ndarray:
    """The clamped PI around the first-order motor, by explicit Euler on a fine grid."""
    y = z = 0.0
    ts = np.arange(0.0, T[-1] + dt / 2, dt)
    out = np.empty(ts.size)
    lim = B * TOP
    for k, t in enumerate(ts):
        out[k] = y
        u = 0.0 if t < 0.1 else n_rpm
        if reverse_at_s is not None and t >= reverse_at_s:
            u = -n_rpm
        e = u - y
        c = A * e + C * z
        clipped = abs(c) > lim
        c = max(min(c, lim), -lim)
        if windup or not clipped or (c > 0) != (e > 0):
            z += e * dt
        y += (c - B * y) * dt
    return np.interp(T, ts, out)


@pytest.mark.parametrize("reverse_at_s", [None, 1.5])
def test_windup_follows_the_euler_reference(reverse_at_s):
    got = _wheel(Effects(windup_top_speed_rpm=TOP), reverse_at_s=reverse_at_s)
    ref = _euler(300.0, windup=True, reverse_at_s=reverse_at_s)
    # sub-steps of 1 ms, the clamp decided at each sub-step's start
    assert np.abs(got - ref).max() < 1.0


def test_the_integrator_winds_up_while_clamped_and_overshoots_more_than_saturation():
    wind = _wheel(Effects(windup_top_speed_rpm=TOP))
    sat = _wheel(Effects(top_speed_rpm=TOP))
    assert sat.max() < 306.0  # anti-windup: hardly more than the linear loop's overshoot
    assert wind.max() > sat.max() + 10.0
    assert wind.max() <= TOP + 1e-6  # the clamp still holds the wheel below its top speed
    assert wind[-1] == pytest.approx(300.0, abs=0.5) and sat[-1] == pytest.approx(300.0, abs=0.5)


def test_an_output_limit_never_reached_leaves_windup_the_linear_model():
    small = _wheel(Effects(windup_top_speed_rpm=TOP), n_rpm=50.0)
    assert np.abs(small - _wheel(Effects(), n_rpm=50.0)).max() < 1e-9


@pytest.mark.parametrize("extra", [{"controller_period_s": 0.004}, {"drive_lag_s": 0.005},
                                   {"breakaway_rpm_per_s": 500.0}])
def test_windup_on_the_drive_dynamics_path_overshoots_as_on_the_closed_form(extra):
    wind = _wheel(Effects(windup_top_speed_rpm=TOP, **extra))
    sat = _wheel(Effects(top_speed_rpm=TOP, **extra))
    assert wind.max() > sat.max() + 5.0
    assert wind[-1] == pytest.approx(300.0, abs=1.0)


def test_windup_round_trips_through_the_calibration_file(tmp_path):
    cal = Calibration(A, B, C, effects=Effects(windup_top_speed_rpm=412.5, dead_time_s=0.01))
    back = load_calibration(save_calibration(cal, tmp_path / "w.toml"))
    assert back.effects == cal.effects
    assert "[effects.windup]" in (tmp_path / "w.toml").read_text()


def test_windup_and_saturation_are_not_in_one_model(tmp_path):
    with pytest.raises(ConfigError, match="saturation and windup"):
        Effects(top_speed_rpm=300.0, windup_top_speed_rpm=300.0)
    path = tmp_path / "both.toml"
    path.write_text("[motor]\nA = 20.0\nB = 15.0\nC = 400.0\n[effects.saturation]\n"
                    "top_speed_rpm = 300.0\n[effects.windup]\nwindup_top_speed_rpm = 300.0\n")
    with pytest.raises(ConfigError, match=r"both\.toml.*saturation and windup"):
        load_calibration(path)
    with pytest.raises(ConfigError, match="windup_top_speed_rpm must be > 0"):
        Effects(windup_top_speed_rpm=0.0)


def test_a_recording_started_in_steady_state_stays_there_with_windup():
    cal = Calibration(A, B, C, effects=Effects(windup_top_speed_rpm=TOP))
    state = steady_state(cal, [200.0] * 4, [200.0] * 4)
    cmd = np.tile([200.0, 0.0, 90.0], (T.size, 1))
    w = simulate(cmd, T, cal, initial_state=state).wheel_rpm[0, :, 0]
    assert np.abs(w - 200.0).max() < 1e-6
