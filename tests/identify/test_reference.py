"""The generic reference model (identify/diagnose/reference.py): a diverging trial gives
bounded, finite residuals, and its forward-difference Jacobian is the residuals' change.
(SciPy's ``lm``, used before, ended in different places on the same data depending on the
process's history: ``test_diagnose_helper`` compares the reference's RMSE between processes
exactly, which it did not pass then.)"""

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
    """The reference's series of ``rec``, end to end; the series; the wheels measured."""
    series = ref._series([rec], ROBOT, 0.002)
    wheels = sorted({w for _, w, *_ in series})
    flat = ref._flat(series, {k: wheels.index(s[1]) for k, s in enumerate(series)})
    return flat, series, len(wheels)


def test_a_diverging_trial_gives_bounded_finite_residuals():
    flat, _, n_wheels = _flat(_ringing_step())
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
    """At the ARX estimate and at the first-order start (most coefficients exactly 0: a step
    relative to |theta| alone, 1e-16, was lost in the residuals' rounding, 27 % off, and
    the refinement of testPid7 stopped on its budget), against central differences."""
    flat, series, n_wheels = _flat(_ringing_step())
    first_order = np.zeros(ref.NA + ref.NB + n_wheels)
    first_order[0], first_order[ref.NA], first_order[ref.NA + ref.NB:] = 0.9, 0.1, 1.0
    for theta in (ref._arx(series, 3, n_wheels), first_order):
        J = ref._jacobian(theta, 3, flat)
        for j in range(theta.size):
            h = 1e-5 * max(abs(theta[j]), 1.0)
            up, down = theta.copy(), theta.copy()
            up[j] += h
            down[j] -= h
            central = (ref._residual(up, 3, flat) - ref._residual(down, 3, flat)) / (2 * h)
            np.testing.assert_allclose(J[:, j], central, rtol=1e-4,
                                       atol=1e-4 * np.abs(central).max() + 1e-9)


def test_a_search_that_never_leaves_diverging_models_is_no_fit(monkeypatch):
    """Every trial diverging (every residual at the bound): no reference model, not the
    search's last point with a cost of 1e16 rpm^2 per sample."""
    monkeypatch.setattr(ref, "_residual", lambda theta, d, flat: np.full(flat.y.size,
                                                                         ref.DIVERGED_RPM))
    assert ref.fit_reference([_ringing_step()], ROBOT) is None
