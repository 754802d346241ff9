"""The paper's model is fitted without SciPy's optimiser or numba (identify/lsq.py,
model/linear.py): the same minimum as SciPy's trust-region method, the exact t quantile, and a
fit of a short recording that loads neither library."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mecanum_hil.identify import fit as fitting
from mecanum_hil.identify.lsq import levenberg_marquardt, t_quantile
from mecanum_hil.io.recording import Recording, write_recording
from mecanum_hil.model import Calibration, RobotProfile, simulate, uniform_time

ROOT = Path(__file__).resolve().parents[2]
ROBOT = RobotProfile()


def test_t_quantile_is_scipys():
    from scipy.special import stdtrit

    for dof in (1, 2, 3, 4.5, 7, 10, 30, 100, 1143, 1e4, 1e6):
        for p in (0.5001, 0.6, 0.9, 0.975, 0.995, 0.9999, 1 - 1e-9, 0.025, 0.1):
            assert t_quantile(p, dof) == pytest.approx(stdtrit(dof, p), rel=1e-10, abs=0)
    assert t_quantile(0.5, 12) == 0.0
    with pytest.raises(ValueError):
        t_quantile(1.0, 5)


def _recording(cal: Calibration, seed: int, rate_hz: float = 500.0) -> Recording:
    """Steps up and down, measured with 3 rpm of noise and a tail a linear model misses."""
    t = uniform_time(2.0, rate_hz)
    cmd = np.zeros((t.size, 3))
    cmd[:, 2] = 90.0
    cmd[:, 0] = np.where(t < 1.0, 120.0, 40.0)
    wheels = simulate(cmd, t, cal, ROBOT).wheel_rpm[0]
    rng = np.random.default_rng(seed)
    meas = (wheels + rng.normal(0, 3.0, wheels.shape)
            - 0.02 * np.maximum(wheels - 100.0, 0) ** 2)
    return Recording(t, cmd, meas, np.full((t.size, 3), np.nan))


@pytest.mark.parametrize("truth", [(14.7, 16.1, 303.0), (0.3, 6.5, 527.0), (2.0, 4.8, 1184.0)])
def test_the_same_minimum_as_scipys_trust_region(truth):
    from scipy.optimize import least_squares

    data = fitting.prepare([_recording(Calibration().with_coefficients(*truth), 4)], ROBOT)
    lo, hi = fitting._bounds(list("ABC"), None)
    problem = fitting._Problem(data, Calibration(), ROBOT, list("ABC"), lo, hi, 0.0)
    solve = fitting._solver(Calibration(), list("ABC"), False)
    for start in fitting._starts(data, Calibration(), ROBOT, list("ABC"), None, lo, hi):
        x0 = np.array([start[n] for n in "ABC"])
        ours = solve(problem, x0, lo, hi, 600)
        ref = least_squares(problem.fun, x0, jac=problem.jac, bounds=(lo, hi), x_scale="jac",
                            method="trf", max_nfev=600)
        assert ours.status in (1, 2, 3, 4)
        assert ours.cost <= ref.cost * (1 + 1e-7)
        assert np.all(ours.x >= lo) and np.all(ours.x <= hi)


def test_an_active_bound_does_not_stall_the_search():
    # min over x >= 0 of (x0 + 1)^2 + 10 (x1 - 2)^2 + (x0 x1): the minimum sits on x0 = 0
    def fun(x):
        return np.array([x[0] + 1.0, np.sqrt(10.0) * (x[1] - 2.0), 0.1 * x[0] * x[1]])

    def jac(x):
        return np.array([[1.0, 0.0], [0.0, np.sqrt(10.0)], [0.1 * x[1], 0.1 * x[0]]])

    sol = levenberg_marquardt(fun, jac, [3.0, -1.0], [0.0, -np.inf], [np.inf, np.inf],
                              max_nfev=50)
    assert sol.x[0] == 0.0 and sol.x[1] == pytest.approx(2.0, abs=1e-6)
    assert sol.status in (1, 2, 3, 4) and sol.nfev < 20


def test_fit_of_a_short_recording_loads_neither_numba_nor_scipy_optimize(tmp_path):
    rec = _recording(Calibration().with_coefficients(14.7, 16.1, 303.0), 5)
    path = tmp_path / "step.csv"
    write_recording(rec, path)
    code = f"""
import json, sys
from mecanum_hil.cli import main
code = main(["fit", {str(path)!r}, "--out", {str(tmp_path / "cal.toml")!r}, "--no-report",
             "--json"])
print(json.dumps({{"code": code, "numba": "numba" in sys.modules,
                  "optimize": "scipy.optimize" in sys.modules}}))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=300, cwd=ROOT)
    lines = out.stdout.strip().splitlines()
    flags = json.loads(lines[-1])
    assert flags == {"code": 0, "numba": False, "optimize": False}
    # the same coefficients as in a process where numba and SciPy are loaded
    import scipy.optimize  # noqa: F401

    fitted = json.loads(lines[0])
    here = fitting.fit([rec], ROBOT)
    for name in "ABC":
        assert fitted[name] == pytest.approx(getattr(here.calibration, name), rel=1e-6)


def test_a_search_where_every_step_fails_is_a_failure():
    # residuals finite at the start only: no step is ever taken, and that is no minimum
    def fun(x):
        return np.array([x[0] - 1.0]) if x[0] == 0.0 else np.array([np.inf])

    sol = levenberg_marquardt(fun, lambda x: np.array([[1.0]]), [0.0], [-np.inf], [np.inf],
                              max_nfev=500)
    assert sol.status == -1 and sol.x[0] == 0.0


def test_a_real_clock_recording_is_fitted_compiled_not_in_numpy(tmp_path):
    # every step length differs (a logger's own clock): the start grid's tables alone would
    # cost seconds in numpy, so the fit loads numba instead (and gives the same answer)
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.009, 0.011, 600))
    t -= t[0]
    cmd = np.zeros((t.size, 3))
    cmd[:, 0], cmd[:, 2] = 60.0, 90.0
    truth = Calibration().with_coefficients(27.0, 8.5, 610.0)
    wheels = simulate(cmd, t, truth, ROBOT).wheel_rpm[0] + rng.normal(0, 0.3, (t.size, 4))
    path = tmp_path / "clock.csv"
    write_recording(Recording(t, cmd, wheels, np.full((t.size, 3), np.nan)), path)
    code = f"""
import json, sys
from mecanum_hil.cli import main
code = main(["fit", {str(path)!r}, "--out", {str(tmp_path / "cal.toml")!r}, "--no-report",
             "--json"])
print(json.dumps({{"code": code, "numba": "numba" in sys.modules}}))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=300, cwd=ROOT)
    lines = out.stdout.strip().splitlines()
    assert json.loads(lines[-1]) == {"code": 0, "numba": True}
    assert json.loads(lines[0])["C"] == pytest.approx(610.0, rel=0.05)
