"""paper-grid: the paper's three passes, each exactly the argmin of an exhaustive evaluation."""

import numpy as np
import pytest

from mecanum_hil.errors import FitError
from mecanum_hil.identify import grid
from mecanum_hil.identify.fit import _sse_of, fit, prepare
from mecanum_hil.io.recording import Recording
from mecanum_hil.model import Calibration, Effects, RobotProfile, simulate, uniform_time
from mecanum_hil.model.motor import discretise

ROBOT = RobotProfile()
TRUE = Calibration(A=27.0, B=8.5, C=610.0)


def recording(cal=TRUE, seed=0, duration_s=1.0, rate_hz=100.0):
    t = uniform_time(duration_s, rate_hz)
    cmd = np.zeros((t.size, 3))
    cmd[:, 0], cmd[:, 2] = 60.0, 90.0
    cmd[t >= 0.6, 1] = 30.0  # a turn: wheels 1, 3 and 2, 4 follow different targets
    w = simulate(cmd, t, cal, ROBOT).wheel_rpm[0]
    w = w + np.random.default_rng(seed).normal(0.0, 0.7, w.shape)
    w[::5, 2] = np.nan
    return Recording(t, cmd, w, np.full((t.size, 3), np.nan))


@pytest.mark.parametrize("A,B,C,h", [
    (25.0, 9.0, 420.0, 0.01),     # complex roots
    (2000.0, 25.5, 1.0, 0.01),    # far apart real roots
    (1.0, 1.0, 0.25, 0.01),       # repeated root
    (1.0, 1.0, 0.2500001, 0.3),   # nearly repeated
    (0.0, 1.0, 1.0, 0.01),
    (100.0, 3.0, 5000.0, 0.002),
    (2000.0, 5.0, 2000.0, 1.0),   # long step, stiff
])
def test_closed_form_discretisation_matches_the_matrix_exponential(A, B, C, h):
    got = np.array(grid.discretise_closed_form(A, B, C, h))
    ref = discretise(A, B, C, h)[:6]
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-13)


def test_kernel_sse_equals_the_simulator_sse():
    data = prepare([recording()], ROBOT)
    g = grid.grid_data(data, Calibration(), ROBOT)
    pts = np.array([[27.0, 8.5, 610.0], [10.0, 15.5, 300.0], [2000.0, 25.0, 2000.0],
                    [3.0, 0.0, 7.0]])
    ref = _sse_of(data, [Calibration(A=a, B=b, C=c) for a, b, c in pts], ROBOT)
    np.testing.assert_allclose(grid.evaluate_points(g, pts), ref, rtol=1e-9)
    # points that are not a stable model are excluded
    assert np.isinf(grid.evaluate_points(g, [[5.0, 5.0, 0.0], [0.0, 0.0, 5.0]])).all()


def brute_force_pass(data, a, b, c):
    """Exhaustive evaluation with the simulator; first of the least SSE in A, B, C order."""
    pts = np.array(np.meshgrid(a, b, c, indexing="ij")).reshape(3, -1).T
    ok = (pts[:, 2] > 0) & (pts[:, 0] + pts[:, 1] > 0)
    sse = np.full(pts.shape[0], np.inf)
    sse[ok] = _sse_of(data, [Calibration(A=p[0], B=p[1], C=p[2]) for p in pts[ok]], ROBOT)
    i = int(np.argmin(sse))
    return tuple(pts[i]), sse[i]


def test_paper_grid_equals_brute_force_over_a_smaller_grid():
    data = prepare([recording(seed=1)], ROBOT)
    a_spec, b_spec, c_spec = (0, 60, 2), (5.5, 25.5, 1.0), (0, 900, 30)
    res = grid.paper_grid(data, Calibration(), ROBOT, a_grid=a_spec, b_grid=b_spec,
                          c_grid=c_spec, b_start=15.5)
    a, b, c = grid.axis(a_spec), grid.axis(b_spec), grid.axis(c_spec)
    p1, _ = brute_force_pass(data, a, [15.5], c)
    p2, _ = brute_force_pass(data, [p1[0]], b, [p1[2]])
    p3, sse3 = brute_force_pass(data, a, [p2[1]], c)
    assert [p[:3] for p in res.passes] == [p1, p2, p3]
    assert (res.A, res.B, res.C) == p3
    assert res.sse == pytest.approx(sse3, rel=1e-9)
    # and the FitResult carries the grid's point and settings
    out = fit([recording(seed=1)], ROBOT, "paper-grid", a_grid=a_spec, b_grid=b_spec,
              c_grid=c_spec)
    assert (out.calibration.A, out.calibration.B, out.calibration.C) == p3
    assert out.calibration.info["grid_a"] == "0:60:2"


def test_pruned_rows_give_the_exhaustive_argmin_including_ties():
    data = prepare([recording(seed=2)], ROBOT)
    g = grid.grid_data(data, Calibration(), ROBOT)
    a = np.array([30.0, 27.0, 27.0, 5.0])       # a repeated value makes exact ties
    b = np.array([8.5, 9.0])
    c = np.array([0.0, 610.0, 610.0, 200.0, 900.0])
    full = grid.evaluate_points(g, np.array(np.meshgrid(a, b, c, indexing="ij"))
                                .reshape(3, -1).T)
    i = int(np.argmin(full))
    ia, ib, ic = np.unravel_index(i, (a.size, b.size, c.size))
    assert (ia, ic) == (1, 1)  # the first of the tied points
    A, B, C, sse = grid.grid_argmin(g, a, b, c)
    assert (A, B, C) == (a[ia], b[ib], c[ic]) and sse == full[i]


def host_timed_recording(seed=3):
    """A step after a second at rest, timed as a host receives it: jitter of up to 1.5 ms
    gives every step its own length, and a zero command leaves the wheels at rest."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(np.r_[0.0, 0.01 + rng.uniform(-0.0015, 0.0015, 299)])
    t = np.round(t, 6)
    cmd = np.zeros((t.size, 3))
    cmd[:, 2] = 90.0
    cmd[t >= 1.0, 0] = 60.0
    w = simulate(cmd, t, TRUE, ROBOT).wheel_rpm[0] + rng.normal(0.0, 0.5, (t.size, 4))
    return Recording(t, cmd, w, np.full((t.size, 3), np.nan))


def test_host_timed_steps_give_the_exhaustive_sse_and_argmin():
    data = prepare([host_timed_recording()], ROBOT)
    g = grid.grid_data(data, Calibration(), ROBOT)
    assert g.h_s.size > 100  # many step lengths, each discretised when first needed
    pts = np.array([[27.0, 8.5, 610.0], [10.0, 15.5, 300.0], [2000.0, 25.0, 2000.0]])
    ref = _sse_of(data, [Calibration(A=a, B=b, C=c) for a, b, c in pts], ROBOT)
    np.testing.assert_allclose(grid.evaluate_points(g, pts), ref, rtol=1e-9)
    a, b, c = grid.axis((0, 60, 3)), [8.5], grid.axis((0, 900, 45))
    full = grid.evaluate_points(g, np.array(np.meshgrid(a, b, c, indexing="ij"))
                                .reshape(3, -1).T)
    i = int(np.argmin(full))
    ia, _, ic = np.unravel_index(i, (a.size, 1, c.size))
    A, B, C, sse = grid.grid_argmin(g, a, b, c)
    assert (A, B, C) == (a[ia], 8.5, c[ic]) and sse == full[i]


def test_grid_axis_is_free_of_rounding_and_rejects_bad_specs():
    b = grid.axis(grid.PAPER_B_GRID)
    assert b.size == 201 and b[100] == 15.5 and b[-1] == 25.5
    assert grid.axis(grid.PAPER_A_GRID).size == 2001
    for bad in [(0, 10, 0), (10, 0, 1), (0, 1)]:
        with pytest.raises(FitError):
            grid.axis(bad)


def test_grid_handles_dead_time_and_refuses_nonlinear_effects():
    true = Calibration(A=27.0, B=8.5, C=610.0, effects=Effects(dead_time_s=0.025))
    rec = recording(true, seed=3)
    fixed = Calibration(effects=Effects(dead_time_s=0.025))
    data = prepare([rec], ROBOT)
    g = grid.grid_data(data, fixed, ROBOT)
    pts = np.array([[27.0, 8.5, 610.0], [12.0, 4.0, 100.0]])
    ref = _sse_of(data, [Calibration(A=p[0], B=p[1], C=p[2], effects=fixed.effects)
                         for p in pts], ROBOT)
    np.testing.assert_allclose(grid.evaluate_points(g, pts), ref, rtol=1e-9)
    with pytest.raises(FitError, match="linear model"):
        grid.grid_data(data, Calibration(effects=Effects(top_speed_rpm=80.0)), ROBOT)


@pytest.mark.slow
def test_full_paper_grid_on_a_one_second_step():
    rec = recording(seed=4)
    res = fit([rec], ROBOT, "paper-grid")
    lsq = fit([rec], ROBOT)
    assert lsq.sse <= res.sse * (1 + 1e-12)
    assert res.calibration.info["grid_points"] == 2 * 2001 * 2001 + 201
