"""The generic reference model (identify/diagnose/reference.py): a diverging trial gives
bounded, finite residuals; the fit is the same whatever the process did before (SciPy's ``lm``
was not: 8.862 or 8.872 rpm on testPid8 in one process); its forward-difference Jacobian
matches the residuals' change. ``test_diagnose_helper`` compares the reference's RMSE between
processes exactly."""

from __future__ import annotations

import numpy as np

from mecanum_hil.identify.diagnose import reference as ref
from mecanum_hil.io.recording import Recording
from mecanum_hil.model import Calibration, Effects, RobotProfile
from mecanum_hil.model.simulate import simulate

ROBOT = RobotProfile()


def _ringing_step() -> Recording:
    """A 2-s step at 500 Hz through a dead time, with noise: an ARX start that rings."""
    t = np.arange(1001) / 500.0
    cmd = np.tile([0.0, 0.0, 90.0], (t.size, 1))
    cmd[t >= 0.2, 0] = 150.0
    truth = Calibration(A=3.0, B=8.0, C=500.0, effects=Effects(dead_time_s=0.03))
    w = simulate(cmd, t, truth, ROBOT).wheel_rpm[0]
    w = w + np.random.default_rng(1).normal(0.0, 3.0, w.shape)
    return Recording(t, cmd, w, np.full((t.size, 3), np.nan))


def _flat(rec: Recording):
    series = ref._series([rec], ROBOT, 0.002)
    wheels = sorted({w for _, w, *_ in series})
    return ref._flat(series, {k: wheels.index(s[1]) for k, s in enumerate(series)}), len(wheels)


def test_a_diverging_trial_gives_bounded_finite_residuals():
    flat, n_wheels = _flat(_ringing_step())
    theta = np.zeros(ref.NA + ref.NB + n_wheels)
    theta[0] = 3.0  # |pole| > 1: the recursion overflows to inf, then NaN
    theta[ref.NA] = 1.0
    theta[ref.NA + ref.NB:] = 1.0
    with np.errstate(over="ignore", invalid="ignore"):
        raw = flat.y - ref._simulate_flat(theta, 0, flat)
        r = ref._residual(theta, 0, flat)
    assert not np.isfinite(raw).all()  # the case is one that diverges
    assert np.isfinite(r).all() and np.abs(r).max() <= ref.DIVERGED_RPM


def test_the_jacobian_is_the_residuals_change():
    flat, n_wheels = _flat(_ringing_step())
    series = ref._series([_ringing_step()], ROBOT, 0.002)
    theta = ref._arx(series, 3, n_wheels)
    J = ref._jacobian(theta, 3, flat)
    rng = np.random.default_rng(0)
    step = 1e-6 * rng.normal(size=theta.size) * np.maximum(np.abs(theta), 1e-3)
    change = ref._residual(theta + step, 3, flat) - ref._residual(theta, 3, flat)
    np.testing.assert_allclose(J @ step, change, rtol=1e-3, atol=1e-6 * np.abs(change).max())


def test_the_reference_fit_does_not_depend_on_what_ran_before():
    rec = _ringing_step()
    first = ref.fit_reference([rec], ROBOT)
    assert first is not None and first.rmse_rpm < 3.5  # the noise is 3 rpm
    rng = np.random.default_rng(2)
    junk = [np.ones(int(n)) for n in rng.integers(1, 5000, size=40)]
    assert ref.fit_reference([rec], ROBOT) == first
    del junk
