"""Start values of the ``friction`` and ``drive_deadband`` candidates, read off simulated
recordings: the offset a proportional loop's levels show, and the switch-off level."""

from __future__ import annotations

import numpy as np
import pytest

from mecanum_hil.identify.diagnose import candidates
from mecanum_hil.identify.diagnose.localise import _Evaluator
from mecanum_hil.io.recording import Recording
from mecanum_hil.model import Calibration, Effects, RobotProfile
from mecanum_hil.model.simulate import simulate, uniform_time

ROBOT = RobotProfile()
T = uniform_time(6.0, 200)


def _recording(levels: tuple[float, ...], cal: Calibration, seed: int = 0) -> Recording:
    """Straight-ahead holds of 1 s at each level of ``levels`` [rpm], after 0.1 s at rest,
    with 0.3 rpm of noise."""
    cmd = np.zeros((T.size, 3))
    cmd[:, 2] = 90.0
    for k, level in enumerate(levels):
        cmd[T >= 0.1 + k, 0] = level
    w = simulate(cmd, T, cal, ROBOT).wheel_rpm[0]
    w = w + np.random.default_rng(seed).normal(0.0, 0.3, w.shape)
    return Recording(T, cmd, w, np.full((T.size, 3), np.nan))


P_ONLY = (40.0, 5.0, 1e-3)  # level A / (A + B) = 0.89, next to no integral


def test_a_proportional_loop_s_level_offset_gives_the_friction():
    cal = Calibration(*P_ONLY, effects=Effects(friction_rpm_per_s=600.0))
    ev = _Evaluator([_recording((60.0, 120.0, 200.0, -90.0, 150.0, 0.0), cal)], ROBOT)
    # (A u - F sign(u)) / (A + B): short by F / (A + B) at every level
    assert candidates._level_offset_rpm(ev) == pytest.approx(600.0 / 45.0, abs=0.5)
    start = candidates._friction_start(ev, Calibration(*P_ONLY), 0.3)
    assert start == pytest.approx(600.0, rel=0.05)


def test_levels_on_their_targets_show_no_offset():
    cal = Calibration(14.7, 16.1, 303.0, effects=Effects(friction_rpm_per_s=600.0))
    ev = _Evaluator([_recording((60.0, 120.0, 200.0, -90.0, 150.0, 0.0), cal)], ROBOT)
    assert candidates._level_offset_rpm(ev) < 0.5


def test_the_drive_deadband_is_found_between_the_targets_it_switches_off_and_on():
    truth = Calibration(14.7, 4.0, 303.0, effects=Effects(drive_deadband_rpm=25.0))
    rec = _recording((60.0, 20.0, 120.0, 10.0, -40.0, 0.0), truth)
    ev = _Evaluator([rec], ROBOT)
    start = Calibration(14.0, 6.0, 280.0)  # the coefficients a fit without it gives roughly
    fitted = candidates.fit_candidate(ev, "drive_deadband", start, ["A", "B", "C"], ["r"], 0.3)
    found = fitted.calibration.effects.drive_deadband_rpm
    # 20 rpm switched off, 40 rpm on: any level between is the same model
    assert 20.0 < found <= 40.0
    assert fitted.calibration.B == pytest.approx(4.0, rel=0.1)  # the coasting shows the pole
