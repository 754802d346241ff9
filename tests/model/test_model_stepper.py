"""The array stepper reproduces one long simulate() call, period by period."""

from __future__ import annotations

import numpy as np
import pytest

from mecanum_hil.errors import ConfigError
from mecanum_hil.model import Calibration, Effects, simulate, stepper
from mecanum_hil.model.motor import discretise
from mecanum_hil.model.stepper import BatchStepper, discretise_many, step_plan, step_tables

EFFECTS = {
    "linear": Effects(),
    "dead_time_whole_periods": Effects(dead_time_s=0.04),
    "dead_time_split": Effects(dead_time_s=0.033),
    "all_effects": Effects(dead_time_s=0.013, top_speed_rpm=90.0, rate_limit_rpm_per_s=300.0,
                           deadband_rpm=3.0, gains=(1.0, 0.9, 1.0, 1.1),
                           efficiency=(0.9, 0.8, 0.95)),
    "drive_dynamics": Effects(controller_period_s=0.006, breakaway_rpm_per_s=900.0,
                              braking_limit_rpm_per_s=700.0, dead_time_s=0.02),
    "fast_decay": Effects(coast_decel_rpm_per_s=600.0, no_load_rpm=150.0,
                          controller_period_s=0.006, dead_time_s=0.02),
    "windup": Effects(windup_top_speed_rpm=60.0, dead_time_s=0.013, rate_limit_rpm_per_s=900.0),
    "windup_drive": Effects(windup_top_speed_rpm=60.0, controller_period_s=0.006,
                            drive_lag_s=0.01),
    "friction": Effects(friction_rpm_per_s=400.0, dead_time_s=0.013),
    "friction_drive": Effects(friction_rpm_per_s=400.0, controller_period_s=0.006,
                              drive_lag_s=0.01, breakaway_rpm_per_s=600.0, top_speed_rpm=70.0),
    "drive_deadband": Effects(drive_deadband_rpm=25.0, friction_rpm_per_s=300.0,
                              rate_limit_rpm_per_s=900.0),
    "drive_deadband_drive": Effects(drive_deadband_rpm=25.0, controller_period_s=0.006,
                                    drive_lag_s=0.01, coast_decel_rpm_per_s=400.0),
}


def _commands(rng, T):
    return np.column_stack([rng.uniform(0, 80, T), rng.uniform(-40, 40, T),
                            rng.uniform(-180, 180, T)])


def test_compiled_discretisation_matches_scipy():
    co = np.array([[14.7, 16.1, 303.0], [1.0, 0.0, 5.0], [40.0, 2.0, 900.0]])
    h = np.array([0.02, 0.001, 0.37])
    ref = discretise(co[:, 0:1], co[:, 1:2], co[:, 2:3], h[None, :])
    np.testing.assert_allclose(discretise_many(co, h), ref, rtol=1e-12, atol=1e-12)


def test_compiled_discretisation_matches_scipy_over_the_whole_range():
    # real, repeated and complex poles, tiny C, A << A + B, long and short steps: the closed
    # form where it is well conditioned and the series elsewhere both match, each entry to
    # 1e-8 of its natural scale (1 for Ad, C h for a12, h for cq1, ...)
    rng = np.random.default_rng(0)
    co = np.column_stack([10 ** rng.uniform(-2, 3.5, 600), 10 ** rng.uniform(-2, 3, 600),
                          10 ** rng.uniform(-6, 6, 600)])
    co = np.vstack([co, [[14.7, 16.1, (30.8 / 2) ** 2 * (1 + e)] for e in (0, 1e-9, -1e-5)],
                    [[0.0, 5.0, 6.25], [0.04, 81.0, 0.11]]])
    h = 10 ** rng.uniform(-4, 0.3, 25)
    got = discretise_many(co, h)[..., :10]
    ref = discretise(co[:, 0:1], co[:, 1:2], co[:, 2:3], h[None, :])[..., :10]
    A, C, H = co[:, 0:1], co[:, 2:3], h[None, :]
    one = np.ones_like(A * H)
    scale = np.stack([one, C * H, one * H, one, A * H + C * H * H, one * H, one * H, C * H * H,
                      A * H * H + C * H ** 3, one], axis=-1)
    err = np.abs(got - ref) / np.maximum(scale, 1e-300)
    assert err.max() < 1e-8, np.unravel_index(np.argmax(err), err.shape)


def test_tables_follow_each_robots_coefficients():
    co = np.array([[14.7, 16.1, 303.0], [20.0, 10.0, 200.0], [14.7, 16.1, 303.0]])
    tables = step_tables(co, [0.02])
    assert tables.shape == (3, 1, 11)
    np.testing.assert_array_equal(tables[0], tables[2])
    np.testing.assert_allclose(tables[1, 0], discretise(20.0, 10.0, 200.0, 0.02), atol=1e-12)


def test_table_cache_overflow_keeps_every_requested_set(monkeypatch):
    monkeypatch.setattr(stepper, "_CACHE_LIMIT", 4)
    monkeypatch.setattr(stepper, "_TABLE_CACHE", {})
    first = np.array([[14.7, 16.1, 303.0], [20.0, 10.0, 200.0], [5.0, 30.0, 500.0]])
    step_tables(first, [0.02])
    mixed = np.vstack([first[:2], [[7.0, 7.0, 70.0], [8.0, 8.0, 80.0]]])
    tables = step_tables(mixed, [0.02])
    np.testing.assert_allclose(tables[3, 0], discretise(8.0, 8.0, 80.0, 0.02), atol=1e-12)
    np.testing.assert_allclose(tables[0, 0], discretise(14.7, 16.1, 303.0, 0.02), atol=1e-12)


def test_step_plan_splits_at_the_delayed_command_change():
    plan = step_plan(0.02, Effects(dead_time_s=0.033))
    assert plan.delay_periods == 1
    np.testing.assert_allclose(plan.piece_s, [0.013, 0.007])
    assert step_plan(0.02, Effects(dead_time_s=0.04)).piece_s.size == 1
    with pytest.raises(ConfigError):
        step_plan(0.0, Effects())


@pytest.mark.parametrize("held", [1, 5], ids=["new-command-each-period", "held-5-periods"])
@pytest.mark.parametrize("name", sorted(EFFECTS))
def test_stepping_equals_one_simulate_call(name, held):
    # commands held for several periods too (an agent's action repeated): the simulator's grid
    # and the stepper's cuts must stay the same where the delayed command does not change
    rng = np.random.default_rng(7)
    T, h = 120, 0.02
    cmd = np.repeat(_commands(rng, -(-T // held)), held, axis=0)[:T]
    cal = Calibration(effects=EFFECTS[name])
    ref = simulate(cmd, np.arange(T) * h, cal, initial_pose=(0.5, -1.0, 30.0))
    st = BatchStepper(1, h, cal)
    st.reset(pose=(0.5, -1.0, 30.0))
    poses, wheels = [st.pose[0].copy()], [st.wheel_rpm[0].copy()]
    for k in range(T - 1):
        st.step(cmd[k][None])
        poses.append(st.pose[0].copy())
        wheels.append(st.wheel_rpm[0].copy())
    np.testing.assert_allclose(poses, ref.pose[0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(wheels, ref.wheel_rpm[0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(st.state[0], ref.final_state[0], rtol=0, atol=1e-9)


def test_robots_with_their_own_coefficients_equal_separate_simulations():
    rng = np.random.default_rng(3)
    T, h = 60, 0.02
    cmd = np.stack([_commands(rng, T) for _ in range(3)])
    co = np.array([[14.7, 16.1, 303.0], [20.0, 10.0, 200.0], [5.0, 30.0, 500.0]])
    eff = EFFECTS["dead_time_split"]
    st = BatchStepper(3, h, Calibration(effects=eff))
    st.set_coefficients(co)
    st.reset()
    for k in range(T - 1):
        st.step(cmd[:, k])
    for i in range(3):
        cal = Calibration(*co[i], effects=eff)
        ref = simulate(cmd[i], np.arange(T) * h, cal)
        np.testing.assert_allclose(st.pose[i], ref.pose[0, -1], atol=1e-9)
        np.testing.assert_allclose(st.state[i], ref.final_state[0], atol=1e-9)


def test_unstable_coefficients_are_refused():
    st = BatchStepper(2, 0.02, Calibration())
    with pytest.raises(ConfigError):
        st.set_coefficients([1.0, 1.0, -5.0], index=[1])
