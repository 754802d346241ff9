"""The paper's model in numpy (mecanum_hil/model/linear.py) gives the batch simulator's wheel
speeds: uniform and jittered time grids, ringing and overdamped coefficients, the series where
the closed form loses digits, and a start in motion."""

from __future__ import annotations

import numpy as np
import pytest

from mecanum_hil.model import Calibration, linear
from mecanum_hil.model.discretise import discretise_many
from mecanum_hil.model.kinematics import command_to_wheels
from mecanum_hil.model.linear import wheel_speeds, zoh_tables
from mecanum_hil.model.robot import RobotProfile
from mecanum_hil.model.simulate import simulate_batch, steady_state

COEFFICIENTS = np.array([
    [14.7, 16.1, 303.0],      # the paper's
    [2.0, 4.8, 1184.0],       # a micromouse's: integral-dominated, ringing
    [0.0, 6.5, 527.0],        # no proportional action: the series
    [300.0, 50.0, 1.0],       # overdamped, C h^2 tiny: the series
    [1000.0, 3000.0, 1e6],    # fast
])


def test_tables_equal_the_compiled_discretisation():
    rng = np.random.default_rng(0)
    co = np.column_stack([10 ** rng.uniform(-1, 3.5, 300), 10 ** rng.uniform(-1, 3, 300),
                          10 ** rng.uniform(0, 6, 300)])
    co = np.vstack([co, COEFFICIENTS])
    h = np.array([0.0005, 0.001, 0.002, 0.01, 0.1])
    ours = zoh_tables(co, h)
    ref = discretise_many(co, h)[..., :6]
    # each entry on its natural scale (a12 ~ C h, b2 ~ h)
    scale = np.ones_like(ref)
    scale[..., 1] = np.maximum(co[:, 2:3] * h, 1.0)
    np.testing.assert_allclose(ours / scale, ref / scale, rtol=0, atol=1e-9)


@pytest.mark.parametrize("jitter", [False, True])
def test_wheel_speeds_equal_the_simulator(jitter):
    rng = np.random.default_rng(1)
    T = 240
    t = np.arange(T) * 0.004
    if jitter:
        t = np.cumsum(rng.choice([0.003, 0.004, 0.005], T)) - 0.003
    cmd = np.column_stack([np.repeat(rng.uniform(-80, 80, 8), 30),
                           np.repeat(rng.uniform(-40, 40, 8), 30),
                           np.repeat(rng.uniform(-180, 180, 8), 30)])
    robot = RobotProfile()
    targets = command_to_wheels(cmd[:, 0], cmd[:, 1], cmd[:, 2], robot.k)
    h_s, h_idx = np.unique(np.diff(t), return_inverse=True)
    ours = wheel_speeds(COEFFICIENTS, h_s, h_idx, targets.T)
    cals = [Calibration().with_coefficients(*c) for c in COEFFICIENTS]
    ref = simulate_batch(np.broadcast_to(cmd, (len(cals), T, 3)), t, cals, robot).wheel_rpm
    np.testing.assert_allclose(ours.transpose(0, 2, 1), ref, rtol=0, atol=1e-9)


def test_a_start_in_motion_equals_the_simulator_from_steady_state():
    T = 200
    t = np.arange(T) * 0.002
    cmd = np.tile([120.0, 0.0, 90.0], (T, 1))
    cmd[100:, 0] = 60.0
    robot = RobotProfile()
    targets = command_to_wheels(cmd[:, 0], cmd[:, 1], cmd[:, 2], robot.k)
    start = np.array([95.0, 97.0, 110.0, 101.0])
    cals = [Calibration().with_coefficients(*c) for c in COEFFICIENTS]
    states = np.stack([steady_state(c, start, targets[0]) for c in cals])
    ref = simulate_batch(np.broadcast_to(cmd, (len(cals), T, 3)), t, cals, robot,
                         initial_state=states, initial_command=cmd[0]).wheel_rpm
    A, B, C = (COEFFICIENTS[:, i:i + 1] for i in range(3))
    z0 = (B * start - A * (targets[0] - start)) / C
    ours = wheel_speeds(COEFFICIENTS, [0.002], np.zeros(T - 1, int), targets.T, start, z0)
    np.testing.assert_allclose(ours.transpose(0, 2, 1), ref, rtol=0, atol=1e-9)


@pytest.mark.parametrize("T", [1, 2, 3, 240, 9000])
def test_the_scan_equals_stepping(T):
    """Few sets x series run as a prefix scan, in chunks of SCAN_CHUNK steps; many step by
    step: the same speeds to rounding, across chunk boundaries and from a start in motion."""
    rng = np.random.default_rng(T)
    h_s = np.array([0.001, 0.002, 0.0035])
    h_idx = rng.integers(0, h_s.size, max(T - 1, 0))
    targets = np.repeat(rng.uniform(-150, 150, (4, T // 30 + 1)), 30, axis=1)[:, :T]
    y0 = rng.uniform(-60, 60, (len(COEFFICIENTS), 4))
    z0 = rng.uniform(-0.5, 0.5, (len(COEFFICIENTS), 4))
    tab = zoh_tables(COEFFICIENTS, h_s)
    assert len(COEFFICIENTS) * 4 <= linear.SCAN_MAX_SERIES
    scanned = wheel_speeds(COEFFICIENTS, h_s, h_idx, targets, y0, z0)
    stepped = linear._stepwise(tab, h_idx, targets, y0, z0)
    assert scanned.shape == stepped.shape == (len(COEFFICIENTS), 4, T)
    np.testing.assert_allclose(scanned, stepped, rtol=0, atol=1e-9)
    # and through the public function when the sets are many
    many = np.repeat(COEFFICIENTS, 2, axis=0)
    assert many.shape[0] * 4 > linear.SCAN_MAX_SERIES
    np.testing.assert_allclose(wheel_speeds(many, h_s, h_idx, targets)[::2],
                               wheel_speeds(COEFFICIENTS, h_s, h_idx, targets),
                               rtol=0, atol=1e-9)
