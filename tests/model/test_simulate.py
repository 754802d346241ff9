"""The simulator: exactness, worked runs (distance, turn, circle), batch = single, effects."""

from dataclasses import replace

import numpy as np
import pytest
from scipy import signal

from mecanum_hil.errors import ConfigError
from mecanum_hil.model import (
    Calibration,
    Effects,
    RobotProfile,
    simulate,
    simulate_batch,
    uniform_time,
)
from mecanum_hil.model.motor import transfer_function
from mecanum_hil.units import rpm_to_mps

PAPER = Calibration()
ROBOT = RobotProfile()


def hold(n, omega, theta, t):
    return np.tile([n, omega, theta], (t.size, 1)).astype(float)


def test_unit_step_response_values():
    t = uniform_time(0.2, 1000)
    w = simulate(hold(1, 0, 90, t), t, PAPER).wheel_rpm[0, :, 0]
    got = [w[50], w[100], w[150], w[200]]
    np.testing.assert_allclose(got, [0.5588, 0.8390, 0.9576, 0.9984], atol=5e-5)


def test_matches_analytic_step_response_at_any_rate():
    num, den = transfer_function(*PAPER.coefficients)
    for rate in (7.0, 100.0, 1000.0):
        t = uniform_time(1.0, rate)
        w = simulate(hold(60, 0, 90, t), t, PAPER).wheel_rpm[0, :, 0]
        _, y = signal.step((num, den), T=t)
        np.testing.assert_allclose(w, 60 * y, atol=1e-9)


def test_straight_run_distance():
    t = uniform_time(2.0, 100)
    pose = simulate(hold(120, 0, 90, t), t, PAPER).pose[0, -1]
    expected = rpm_to_mps(120, ROBOT.wheel_radius_m) * (2 - PAPER.B / PAPER.C)
    assert rpm_to_mps(120, ROBOT.wheel_radius_m) == pytest.approx(1.2818, abs=1e-4)
    # default heading 90 deg: theta = 90 (ahead) is world +Y
    assert pose[1] == pytest.approx(expected, rel=1e-9)
    assert pose[0] == pytest.approx(0.0, abs=1e-12)
    assert pose[2] == pytest.approx(90.0)


@pytest.mark.parametrize("theta", [0.0, 30.0, 135.0, 250.0])
def test_translation_goes_in_theta_direction_with_default_heading(theta):
    t = uniform_time(2.0, 50)
    pose = simulate(hold(100, 0, theta, t), t, PAPER).pose[0, -1]
    dist = rpm_to_mps(100, ROBOT.wheel_radius_m) * (2 - PAPER.B / PAPER.C)
    v = dist * float(1 / (abs(np.sin(np.radians(theta))) + abs(np.cos(np.radians(theta)))))
    np.testing.assert_allclose(pose[:2], [v * np.cos(np.radians(theta)),
                                          v * np.sin(np.radians(theta))], atol=1e-9)


def test_turn_angle():
    t = uniform_time(3.0, 100)
    pose = simulate(hold(0, 60, 90, t), t, PAPER).pose[0, -1]
    assert pose[2] - 90.0 == pytest.approx(60 * (3 - PAPER.B / PAPER.C), rel=1e-9)
    np.testing.assert_allclose(pose[:2], 0.0, atol=1e-12)


def test_circle_is_exact_for_constant_twist():
    # after the transient, drive forward while turning: the path must be a circle whose radius
    # is v / w whatever the step size (the pose update is exact for a constant twist)
    state = np.zeros((1, 12))
    state[0, :4] = [-45.588235294117645 + 50, 50 + 45.588235294117645,
                    50 - 45.588235294117645, 50 + 45.588235294117645]
    for rate in (10.0, 1000.0):
        t = uniform_time(6.0, rate)
        # start at the exact steady state of this command so the twist is constant
        cmd = hold(95.588235294117645, 60, 90, t)
        traj = simulate(cmd, t, PAPER, initial_state=_steady_state(cmd[0]))
        xy = traj.pose[0, :, :2]
        v = rpm_to_mps(95.588235294117645, ROBOT.wheel_radius_m) * 1.0
        radius = v / np.radians(60.0)
        centre = np.array([-radius, 0.0])  # heading 90 deg, turning left: centre at -X
        np.testing.assert_allclose(np.hypot(*(xy - centre).T), radius, rtol=1e-9)


def _steady_state(command):
    from mecanum_hil.model import command_to_wheels

    w = command_to_wheels(*command, ROBOT.k)
    state = np.zeros(12)
    state[:4] = w
    state[4:8] = PAPER.B * w / PAPER.C  # drive = C z = B y at rest on the target
    state[8:] = w
    return state


def test_batch_equals_single_with_own_commands_and_coefficients():
    rng = np.random.default_rng(3)
    t = uniform_time(1.5, 200)
    n_rob = 5
    cmds = np.empty((n_rob, t.size, 3))
    for i in range(n_rob):
        cmds[i] = hold(*rng.uniform([0, -40, 0], [90, 40, 360]), t)
        cmds[i, 100:] = [rng.uniform(0, 60), 0, rng.uniform(0, 360)]
    cals = [PAPER.with_coefficients(*rng.uniform([5, 5, 100], [30, 30, 600]))
            for _ in range(n_rob)]
    cals[2] = replace(cals[2], effects=Effects(dead_time_s=0.0123, gains=(1, 0.9, 1, 1.1)))
    cals[3] = replace(cals[3], effects=Effects(top_speed_rpm=50.0, rate_limit_rpm_per_s=300.0))
    batch = simulate_batch(cmds, t, cals)
    for i in range(n_rob):
        single = simulate(cmds[i], t, cals[i])
        np.testing.assert_allclose(batch.wheel_rpm[i], single.wheel_rpm[0], rtol=0, atol=1e-10)
        np.testing.assert_allclose(batch.pose[i], single.pose[0], rtol=0, atol=1e-10)


def test_continuation_equals_one_run():
    t = uniform_time(2.0, 100)
    cmd = hold(80, 20, 60, t)
    cmd[120:] = [40, -30, 200]
    whole = simulate(cmd, t, PAPER)
    first = simulate(cmd[:101], t[:101], PAPER)
    second = simulate(cmd[100:], t[100:], PAPER, initial_state=first.final_state,
                      initial_pose=first.pose[0, -1])
    np.testing.assert_allclose(second.wheel_rpm[0], whole.wheel_rpm[0, 100:], atol=1e-10)
    np.testing.assert_allclose(second.pose[0], whole.pose[0, 100:], atol=1e-10)


def test_irregular_grid_equals_uniform_at_common_samples():
    t = uniform_time(1.0, 100)
    cmd = hold(120, 30, 70, t)
    ref = simulate(cmd, t, PAPER)
    tt = np.sort(np.concatenate([t, t[:-1] + 0.0037]))
    traj = simulate(hold(120, 30, 70, tt), tt, PAPER)
    idx = np.searchsorted(tt, t)
    np.testing.assert_allclose(traj.wheel_rpm[0, idx], ref.wheel_rpm[0], atol=1e-9)
    # the pose is exact for a constant twist, second order otherwise: sub-mm here
    np.testing.assert_allclose(traj.pose[0, idx], ref.pose[0], atol=1e-4)


def test_dead_time_is_an_exact_shift():
    t = uniform_time(1.0, 100)
    cmd = hold(60, 0, 90, t)
    base = simulate(cmd, t, PAPER).wheel_rpm[0]
    late = simulate(cmd, t, replace(PAPER, effects=Effects(dead_time_s=0.05))).wheel_rpm[0]
    np.testing.assert_allclose(late[5:], base[:-5], atol=1e-10)
    np.testing.assert_allclose(late[:6], 0.0, atol=1e-12)


@pytest.mark.parametrize("delay", [0.06, 0.06 - 1e-12, 0.06 + 1e-12, 0.01999999956, 0.0200000004])
def test_dead_time_at_and_near_whole_samples(delay):
    t = np.arange(301) / 100
    cmd = hold(0, 0, 90, t)
    cmd[50:, 0] = 60
    eff = replace(PAPER, effects=Effects(dead_time_s=delay))
    late = simulate(cmd, t, eff).wheel_rpm[0, :, 0]
    base = simulate(cmd, t, PAPER).wheel_rpm[0, :, 0]
    shift = round(delay * 100)
    np.testing.assert_allclose(late[shift:], base[: t.size - shift], atol=1e-4)


def test_fractional_dead_time_matches_fine_grid():
    t = uniform_time(1.0, 100)
    eff = replace(PAPER, effects=Effects(dead_time_s=0.0137))
    coarse = simulate(hold(60, 0, 90, t), t, eff).wheel_rpm[0, :, 0]
    tf = uniform_time(1.0, 10000)
    fine = simulate(hold(60, 0, 90, tf), tf, eff).wheel_rpm[0, ::100, 0]
    np.testing.assert_allclose(coarse, fine, atol=1e-9)


def test_saturation_ceiling_and_slower_rise():
    t = uniform_time(3.0, 200)
    sat = replace(PAPER, effects=Effects(top_speed_rpm=110.0))
    w_sat = simulate(hold(130, 0, 90, t), t, sat).wheel_rpm[0, :, 0]
    w_lin = simulate(hold(130, 0, 90, t), t, PAPER).wheel_rpm[0, :, 0]
    assert w_sat[-1] == pytest.approx(110.0, abs=0.01)
    assert (w_sat[1:] <= w_lin[1:] + 1e-9).all()
    # a command below the ceiling with a gentle transient is hardly affected
    w_low = simulate(hold(30, 0, 90, t), t, sat).wheel_rpm[0, :, 0]
    w_low_lin = simulate(hold(30, 0, 90, t), t, PAPER).wheel_rpm[0, :, 0]
    np.testing.assert_allclose(w_low, w_low_lin, atol=1e-9)


def test_substeps_converge():
    t = uniform_time(2.0, 100)
    sat = replace(PAPER, effects=Effects(top_speed_rpm=100.0, rate_limit_rpm_per_s=400.0))
    a = simulate(hold(120, 0, 90, t), t, sat, max_substep_s=1e-3).wheel_rpm
    b = simulate(hold(120, 0, 90, t), t, sat, max_substep_s=1e-4).wheel_rpm
    assert np.abs(a - b).max() < 0.1


def test_rate_limit_slope():
    t = uniform_time(2.0, 100)
    eff = replace(PAPER, effects=Effects(rate_limit_rpm_per_s=100.0))
    w = simulate(hold(120, 0, 90, t), t, eff).wheel_rpm[0, :, 0]
    # the wheel follows a 100 rpm/s ramp with the model's lag: its slope mid-way is 100 rpm/s
    slope = (w[100] - w[80]) / 0.2
    assert slope == pytest.approx(100.0, rel=0.01)


def test_deadband_gains_and_slip():
    t = uniform_time(2.0, 100)
    db = replace(PAPER, effects=Effects(deadband_rpm=10.0))
    assert np.all(simulate(hold(8, 0, 90, t), t, db).wheel_rpm == 0)
    assert simulate(hold(12, 0, 90, t), t, db).wheel_rpm[0, -1, 0] == pytest.approx(12.0)
    g = replace(PAPER, effects=Effects(gains=(1.0, 0.5, 1.0, 1.0)))
    np.testing.assert_allclose(simulate(hold(100, 0, 90, t), t, g).wheel_rpm[0, -1],
                               [100, 50, 100, 100], atol=1e-6)
    slip = replace(PAPER, effects=Effects(efficiency=(0.5, 1.0, 1.0)))
    straight = simulate(hold(100, 0, 90, t), t, PAPER)
    slipping = simulate(hold(100, 0, 90, t), t, slip)
    np.testing.assert_allclose(slipping.wheel_rpm, straight.wheel_rpm)
    assert slipping.pose[0, -1, 1] == pytest.approx(0.5 * straight.pose[0, -1, 1])


def test_bad_inputs_are_config_errors():
    t = uniform_time(1.0, 10)
    with pytest.raises(ConfigError):
        simulate(hold(1, 0, 90, t)[:-1], t, PAPER)
    with pytest.raises(ConfigError):
        simulate(hold(np.nan, 0, 90, t), t, PAPER)
    with pytest.raises(ConfigError):
        simulate(hold(1, 0, 90, t), t[::-1], PAPER)


def test_a_robot_with_a_dead_time_is_simulated_alike_whatever_its_batch():
    # robots sharing a dead time but not their commands: each one's result is the same as when
    # it runs alone, bit for bit (the pose and the sub-stepped limits depend on where steps are
    # cut, so the grid must not depend on the batch mates' commands)
    t = uniform_time(1.0, 500)
    rng = np.random.default_rng(5)
    cmds = np.empty((4, t.size, 3))
    for i in range(4):
        cmds[i] = hold(30, 20, 45, t)
        for k in rng.choice(np.arange(10, t.size - 10), size=3, replace=False):
            cmds[i, k:] = [rng.uniform(0, 80), rng.uniform(-40, 40), rng.uniform(0, 360)]
    ramped = replace(PAPER, effects=Effects(dead_time_s=0.0137, rate_limit_rpm_per_s=400.0))
    cals = [ramped] * 2 + [replace(PAPER, effects=Effects(dead_time_s=0.0137))] * 2
    batch = simulate_batch(cmds, t, cals)
    for i in range(4):
        single = simulate(cmds[i], t, cals[i])
        np.testing.assert_array_equal(batch.wheel_rpm[i], single.wheel_rpm[0])
        np.testing.assert_array_equal(batch.pose[i], single.pose[0])


def test_compiled_grid_helpers_equal_numpy(monkeypatch):
    """Once the kernels are compiled, a group's whole plan (the dead time's grid, its samples,
    sub-steps and step-length table) comes from one compiled pass (``plan_kernel``, built on
    ``_grid_kernels.delay_plan_kernel`` and ``unique_keys_kernel``): the same arrays, bit for
    bit, as the numpy code the interpreter uses (``plan_cache._delay_plan``, ``_step_lengths``),
    on uniform, jittered, millisecond-rounded and near-coincident sample times, for delays at,
    near and between samples and beyond the end."""
    import importlib

    from mecanum_hil._jit import compiled
    from mecanum_hil.model._grid_kernels import delay_plan_kernel, unique_keys_kernel
    from mecanum_hil.model.stepper import substeps

    sim = importlib.import_module("mecanum_hil.model.plan_cache")
    rng = np.random.default_rng(7)
    fast = sim._kernels_compiled
    for trial in range(400):
        n = int(rng.integers(1, 200))
        t = [np.arange(n) * 0.01,
             np.cumsum(rng.uniform(0.001, 0.02, n)),
             np.round(np.cumsum(rng.choice([0.002, 0.002, 0.013], n)), 3) + 1e5,
             np.cumsum(rng.uniform(1e-9, 0.004, n))][trial % 4]
        delay = float(rng.choice([0.01, 0.02, 0.0351, 1e-10, 2e-9, 0.002 + 5e-10, 10.0,
                                  rng.uniform(0.0, 0.1)]))
        # the two compiled helpers against their numpy references
        grid = sim._delay_plan(t, delay)
        for a, b in zip(grid, compiled(delay_plan_kernel)(t, delay, sim._time_rounding(t)),
                        strict=True):
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)
        dt = np.diff(grid[0])
        if dt.size:
            didx, _, h_uniq = sim._step_lengths(dt, 1e-3)
            key = sim._length_keys(dt / substeps(dt, 1e-3))
            first, rows, ok = compiled(unique_keys_kernel)(key, sim._FEW_LENGTHS)
            if ok:  # (past _FEW_LENGTHS distinct lengths the plan uses numpy's sort)
                np.testing.assert_array_equal(rows, didx)
                np.testing.assert_array_equal(key[first], sim._length_keys(h_uniq))
        # the whole plan of a group (grid, samples, sub-steps, step lengths) in one pass
        for d, most in ((delay, 1e-3), (delay, None), (0.0, 1e-3), (0.0, None)):
            plans = {}
            for on in (False, True):
                monkeypatch.setattr(sim, "_kernels_compiled", (lambda: True) if on else
                                    (lambda: False))
                plans[on] = sim._make_plan(np.asarray(t, dtype=float), d, most)
            for a, b in zip(plans[False], plans[True], strict=True):
                if isinstance(a, np.ndarray):
                    assert a.dtype == b.dtype
                    np.testing.assert_array_equal(a, b)
                else:
                    assert a == b
    # samples closer than the rounding, through a dead time: the grid merges them; the
    # compiled pass hands them to the numpy code, which plans a one-point grid the same way
    # and refuses samples merged away with a clear error
    for t, ok in ((np.array([0.0, 1e-12]), True), (np.arange(40) * 1e-10, False)):
        got = []
        for on in (False, True):
            monkeypatch.setattr(sim, "_kernels_compiled", (lambda: True) if on else
                                (lambda: False))
            if ok:
                got.append(sim._make_plan(t, 0.003, 1e-3))
            else:
                with pytest.raises(ConfigError, match="closer than"):
                    sim._make_plan(t, 0.003, 1e-3)
        for a, b in zip(*got, strict=True):
            np.testing.assert_array_equal(a, b)
    monkeypatch.setattr(sim, "_kernels_compiled", fast)
    # past _FEW_LENGTHS distinct lengths the scan gives up and numpy's sort is used
    key = np.arange(sim._FEW_LENGTHS + 1, dtype=float)[::-1]
    assert not compiled(unique_keys_kernel)(key, sim._FEW_LENGTHS)[2]


@pytest.mark.parametrize("effects", [
    Effects(),
    Effects(dead_time_s=0.0137, gains=(0.9, 1.0, 1.1, 1.0)),
    Effects(top_speed_rpm=40.0, rate_limit_rpm_per_s=400.0),
    Effects(dead_time_s=0.011, breakaway_rpm_per_s=300.0, drive_lag_s=0.01,
            controller_period_s=0.004),
    Effects(coast_decel_rpm_per_s=300.0, no_load_rpm=200.0, dead_time_s=0.005),
])
def test_the_wheels_asked_for_are_those_of_a_full_simulation(effects):
    """``wheels=`` and ``pose=False`` (a fit of measured wheel speeds): the wheels simulated
    are the full simulation's, bit for bit, final state included; the others and the pose are
    NaN, on every path (closed form, sub-stepped limits, the drive's own dynamics, a dead
    time's refined grid), in a batch and from a moving start."""
    t = uniform_time(1.0, 500)
    cmd = hold(30, 20, 45, t)
    cmd[200:] = [60, -30, 120]
    cal = replace(PAPER, effects=effects)
    cals = [cal, replace(cal, A=20.0)]
    start = np.zeros((2, 12))
    start[1, :4] = [5.0, -3.0, 2.0, 1.0]
    full = simulate_batch(cmd, t, cals, initial_state=start)
    some = np.array([True, False, True, False])
    part = simulate_batch(cmd, t, cals, initial_state=start, wheels=some, pose=False)
    np.testing.assert_array_equal(part.wheel_rpm[..., some], full.wheel_rpm[..., some])
    assert np.isnan(part.wheel_rpm[..., ~some]).all() and np.isnan(part.pose).all()
    np.testing.assert_array_equal(part.final_state[:, [0, 2, 4, 6]],
                                  full.final_state[:, [0, 2, 4, 6]])
    nopose = simulate_batch(cmd, t, cals, initial_state=start, pose=False)
    np.testing.assert_array_equal(nopose.wheel_rpm, full.wheel_rpm)
    assert np.isnan(nopose.pose).all()


def test_a_pose_needs_all_four_wheels():
    t = uniform_time(0.1, 100)
    with pytest.raises(ConfigError, match="all four wheels"):
        simulate(hold(10, 0, 90, t), t, PAPER, wheels=np.array([True, True, False, False]))
    with pytest.raises(ConfigError, match="4 booleans"):
        simulate(hold(10, 0, 90, t), t, PAPER, wheels=[1, 1, 0, 0], pose=False)


def test_what_is_remembered_of_an_array_is_only_of_one_declared_unchanging():
    # the simulator keeps an array's bytes (its plans' key) and checks by identity only for
    # arrays declared unchanging: numpy's read-only flag can be set back, and the array a
    # read-only view looks at may be written
    import importlib

    sim = importlib.import_module("mecanum_hil.model.plan_cache")
    t = uniform_time(0.5, 100)
    base = t.copy()
    base.flags.writeable = False
    view = base[:]
    assert sim.array_facts(base) is None and sim.array_facts(view) is None
    assert sim.bytes_of(view) is not sim.bytes_of(view)
    cmd = hold(60, 20, 45, t)
    cal = replace(PAPER, effects=Effects(dead_time_s=0.013))
    before = simulate(cmd, view, cal).wheel_rpm
    base.flags.writeable = True
    base[1:] += 0.002  # the view's times change
    after = simulate(cmd, view, cal).wheel_rpm
    np.testing.assert_array_equal(after, simulate(cmd, view.copy(), cal).wheel_rpm)
    assert not np.array_equal(after, before)
    # declared: the same bytes object each time, and the same result as undeclared
    declared = sim.unchanging(t.copy())
    assert sim.bytes_of(declared) is sim.bytes_of(declared)
    fresh = simulate(cmd, t, cal).wheel_rpm
    kept = sim.unchanging(cmd.copy())
    for _ in range(2):
        np.testing.assert_array_equal(simulate(kept, declared, cal).wheel_rpm, fresh)
    # a bad time grid is still refused, and so are bad commands
    bad = sim.unchanging(np.array([0.0, 0.2, 0.1]))
    with pytest.raises(ConfigError):
        simulate(hold(1, 0, 90, bad), bad, PAPER)
    nan = sim.unchanging(hold(1, 0, 90, t))
    nan[3, 0] = np.nan  # written after it was declared, before any simulation saw it
    with pytest.raises(ConfigError):
        simulate(nan, declared, PAPER)
    # an entry goes with its array
    key = id(declared)
    del declared
    assert key not in sim._FACTS


def test_an_unpickled_array_declared_unchanging_is_remembered():
    # a diagnosis helper's recordings arrive pickled: their dtype is an equal copy of numpy's
    # float64, for which np.asarray(a, dtype=float) is a new view each time, and what is
    # remembered of an array goes by identity (every trial point checked and copied again)
    import importlib
    import pickle

    sim = importlib.import_module("mecanum_hil.model.plan_cache")
    t = pickle.loads(pickle.dumps(uniform_time(0.5, 100)))
    cmd = pickle.loads(pickle.dumps(hold(60, 20, 45, uniform_time(0.5, 100))))
    assert t.dtype is not np.dtype(float) and t.dtype == np.dtype(float)
    declared_t, declared_cmd = sim.unchanging(t), sim.unchanging(cmd)
    cal = replace(PAPER, effects=Effects(dead_time_s=0.013))
    fresh = simulate(cmd.copy(), t.copy(), cal).wheel_rpm
    np.testing.assert_array_equal(simulate(declared_cmd, declared_t, cal).wheel_rpm, fresh)
    assert sim.array_facts(declared_t).get("times") is True
    assert sim.array_facts(declared_cmd).get("finite") is True


@pytest.mark.parametrize("bad", [0.0, -1e-3, float("nan")])
def test_a_sub_step_that_is_no_length_is_refused(bad):
    t = uniform_time(0.1, 100)
    with pytest.raises(ConfigError, match="max_substep_s"):
        simulate(np.tile([60.0, 0.0, 90.0], (t.size, 1)), t,
                 Calibration(effects=Effects(top_speed_rpm=50.0)), max_substep_s=bad)
