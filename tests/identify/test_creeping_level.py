"""The ``creeping_level`` finding: a wheel given a gain below one whose measured level still
moves towards its target is said to creep, not to settle short."""

from __future__ import annotations

import numpy as np
import pytest

from mecanum_hil.identify.diagnose.localise import creeping_levels
from mecanum_hil.io.recording import Recording
from mecanum_hil.model import Calibration, Effects, RobotProfile
from mecanum_hil.model.simulate import simulate, uniform_time

ROBOT = RobotProfile()
T = uniform_time(6.0, 100)


def _recording(truth: Calibration) -> Recording:
    """Holds of 2 s at 150, 80 and -120 rpm after 0.1 s at rest, 0.5 rpm of noise."""
    cmd = np.zeros((T.size, 3))
    cmd[:, 2] = 90.0
    for k, level in enumerate((150.0, 80.0, -120.0)):
        cmd[T >= 0.1 + 2.0 * k, 0] = level
    w = simulate(cmd, T, truth, ROBOT).wheel_rpm[0]
    w = w + np.random.default_rng(3).normal(0.0, 0.5, w.shape)
    return Recording(T, cmd, w, np.full((T.size, 3), np.nan))


def test_a_slow_integral_behind_a_gain_is_named_a_creep():
    # the proportional part settles at 89 %, the integral closes the rest over seconds
    rec = _recording(Calibration(40.0, 5.0, 10.0))
    model = Calibration(40.0, 5.0, 1e-3, effects=Effects(gains=(0.95, 0.95, 0.95, 0.95)))
    found = creeping_levels(model, [rec], ROBOT, [0, 1, 2, 3])
    assert [f.parameters["wheel"] for f in found] == [1.0, 2.0, 3.0, 4.0]
    assert all(f.effect == "creeping_level" for f in found)
    assert found[0].parameters["creep_rpm_per_s"] == pytest.approx(2.0, rel=0.3)


def test_a_level_that_settles_short_is_not_a_creep():
    truth = Calibration(40.0, 5.0, 1e-3)  # no integral: the level sits at 89 % for good
    model = Calibration(40.0, 5.0, 1e-3, effects=Effects(gains=(0.95, 0.95, 0.95, 0.95)))
    assert creeping_levels(model, [_recording(truth)], ROBOT, [0, 1, 2, 3]) == []
    # nor is a creep behind a gain of one
    assert creeping_levels(Calibration(40.0, 5.0, 1e-3), [_recording(Calibration(40.0, 5.0, 10.0))],
                           ROBOT, [0]) == []
