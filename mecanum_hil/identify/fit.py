"""Least-squares identification of the wheel model (and of effect parameters) from recordings.

The engine of ``mecanum-hil fit`` and ``diagnose``: any subset of the named parameters
(:data:`PARAMETER_NAMES`) is estimated jointly by continuous least squares on every measured wheel
sample of every recording, the other parameters held at the calibration's values. The model is the
project's simulator (:func:`mecanum_hil.model.simulate_batch`) driven by the recorded commands,
from rest, exactly as :func:`mecanum_hil.prediction.predict` runs it; one batch call evaluates the
base point and all finite-difference perturbations of a Jacobian together.

Methods (see ``docs/fit.md``):

* ``lsq`` -- :func:`scipy.optimize.least_squares` (trust-region reflective, bounds that keep the
  model stable) from the best points of a logarithmic grid (for the paper's model alone, whose
  cost is smooth: the same bounded least squares by Levenberg-Marquardt without SciPy,
  :mod:`mecanum_hil.identify.lsq`, and on a short recording the model in numpy,
  :mod:`mecanum_hil.model.linear`: numba and SciPy cost more to load than such a fit takes),
  then 95 % Wald intervals
  ``x +- t_{0.975, n-p} sqrt(diag(s^2 (J^T J)^-1))`` with ``s^2 = SSE / (n - p)``.
* ``paper-grid`` -- the paper's three-pass grid search (:mod:`mecanum_hil.identify.grid`).

This module holds the public entry points (:func:`fit`, :func:`fit_parameters`,
:class:`FitResult`) and the result's making (:func:`finish`); the parts live beside it:
:mod:`~mecanum_hil.identify.parameters` (names, bounds, substitution, reported intervals),
:mod:`~mecanum_hil.identify.prepared` (recordings made ready),
:mod:`~mecanum_hil.identify.problem` (residuals, Jacobian, Wald intervals),
:mod:`~mecanum_hil.identify.starts` (start grids and values) and
:mod:`~mecanum_hil.identify.search` (solver, stalls, restarts). Their names used elsewhere are
importable from here too.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from .. import __version__
from .._cores import one_blas_thread
from .._jit import few_threads
from ..errors import FitError
from ..io.recording import Recording
from ..model.calibration import Calibration
from ..model.kinematics import command_to_wheels
from ..model.robot import RobotProfile
from .parameters import (
    COEFFICIENTS,
    DEFAULT_BOUNDS,
    INDEXED,
    PARAMETER_NAMES,
    UNBOUNDED_FACTOR,
    bounded_interval,
    calibration_intervals,
    check_name,
    checked_bounds,
    parameter_value,
    toml_key,
    unbounded,
    with_parameters,
)
from .prepared import Prepared, pose_scale, prepare, source_name
from .problem import Problem, fits_pose, intervals, metrics, residual_rows, residuals, sse_of
from .search import (
    RESTART_GAIN,
    STALL_EVALUATIONS_PER_PARAMETER,
    STALL_MIN_EVALUATIONS,
    SearchStalledError,
    restarted,
    smooth,
    solver,
)
from .starts import FINE_START_GRID, START_GRID, data_start_values, grid_axis, start_points

# The names other modules, tests and benchmarks import from here, by their former names too.
_Problem = Problem
_SearchStalledError = SearchStalledError
_bounds = checked_bounds
_data_start_values = data_start_values
_grid_axis = grid_axis
_residual_rows = residual_rows
_solver = solver
_sse_of = sse_of
_starts = start_points

__all__ = [
    "DEFAULT_BOUNDS",
    "FINE_START_GRID",
    "PARAMETER_NAMES",
    "RESTART_GAIN",
    "STALL_EVALUATIONS_PER_PARAMETER",
    "STALL_MIN_EVALUATIONS",
    "START_GRID",
    "UNBOUNDED_FACTOR",
    "FitResult",
    "bounded_interval",
    "calibration_intervals",
    "few_threads",
    "finish",
    "fit",
    "fit_parameters",
    "one_blas_thread",
    "parameter_value",
    "pose_scale",
    "prepare",
    "residuals",
    "toml_key",
    "unbounded",
    "with_parameters",
]


@dataclass(frozen=True)
class FitResult:
    """Outcome of a fit.

    Attributes
    ----------
    calibration : Calibration
        The input calibration with the fitted values substituted and ``ci95`` (bare TOML keys, see
        :func:`toml_key`; ``None`` where unidentifiable) and ``info`` (metrics, method, data
        sources) filled in.
    parameters : dict[str, float]
        Fitted free parameters, in their units.
    ci95 : dict[str, tuple[float, float]]
        95 % confidence intervals of the free parameters, clipped to their admissible ranges;
        ``(nan, nan)`` where the data cannot bound the parameter (:func:`bounded_interval`).
    rmse_rpm : float
        Root mean square wheel-speed error over all measured wheel samples used [rpm].
    fit_percent : float
        ``100 (1 - ||y - y_model|| / ||y - mean(y)||)`` over the same samples [%].
    sse : float
        Sum of squared wheel-speed errors [rpm^2] (the pose channels are not included).
    n_samples : int
        Number of measured wheel samples used.
    method : str
        ``"lsq"`` or ``"paper-grid"``.
    warnings : tuple of str
        Problems the caller should see (a coefficient not identifiable, a bound reached ...).
    """

    calibration: Calibration
    parameters: dict[str, float]
    ci95: dict[str, tuple[float, float]]
    rmse_rpm: float
    fit_percent: float
    sse: float
    n_samples: int
    method: str
    warnings: tuple[str, ...] = ()


def finish(data, calibration, robot, free, x, method, *, J=None, r=None, pose_weight=0.0,
           lower=None, upper=None, extra_warnings=(), info_extra=None) -> FitResult:
    """Metrics, intervals and provenance for parameters ``x`` of ``free`` (shared by methods)."""
    x = np.asarray(x, dtype=float)
    if J is None or r is None:
        # residuals and Jacobian at one point: one batch
        problem = Problem(data, calibration, robot, free,
                          np.array([DEFAULT_BOUNDS[n][0] for n in free]),
                          np.array([DEFAULT_BOUNDS[n][1] for n in free]), pose_weight,
                          lazy=False)
        r, J = problem.fun(x), problem.jac(x)
    if lower is None or upper is None:
        lower = np.array([DEFAULT_BOUNDS[n][0] for n in free])
        upper = np.array([DEFAULT_BOUNDS[n][1] for n in free])
    tol = 1e-6 * np.maximum(1.0, np.abs(x))
    on_bound = (x <= lower + tol) | (x >= upper - tol)
    half, warnings = intervals(J, r, x, free, on_bound)
    warnings = list(extra_warnings) + warnings
    for i, name in enumerate(free):
        if on_bound[i]:
            edge = lower[i] if x[i] <= lower[i] + tol[i] else upper[i]
            why = ""
            if name == "C" and edge == lower[i]:
                # the commonest corner: the paper's model has no other way to settle short
                why = ("; no integral action is how this model follows a level that settles "
                       "short of the target (a ceiling, a proportional-only loop, a gain): "
                       "`mecanum-hil diagnose` tells which")
            warnings.append(f"{name} = {x[i]:.4g} is at its bound {edge:g}: the data favour the "
                            "edge of the allowed range, and its interval (which assumes an "
                            f"interior optimum) is only indicative{why}")
    params = {n: float(v) for n, v in zip(free, x, strict=True)}
    cal = with_parameters(calibration, params, "the fitted model")
    # without pose channels the search's last residual is the wheels' at x: no new simulation
    # (contiguous, as a fresh simulation's: the sums then run in the same order)
    sse, rmse, fit_pct, n, per = metrics(data, cal, robot,
                                          np.ascontiguousarray(r) if pose_weight == 0 else None)
    ci = {n: bounded_interval(n, float(x[i]), float(x[i] - half[i]), float(x[i] + half[i]))
          or (math.nan, math.nan) for i, n in enumerate(free)}
    info: dict[str, Any] = {
        "method": method,
        "rmse_rpm": rmse,
        "fit_percent": fit_pct,
        "sse": sse,
        "n_samples": n,
        "free": list(free),
        "sources": [p.source for p in data],
        "fit_percent_per_recording": per,
        "tool_version": __version__,
    }
    if pose_weight > 0:
        info["pose_weight"] = float(pose_weight)
    info.update(info_extra or {})
    if warnings:
        info["warnings"] = list(warnings)
    cal = replace(cal, ci95=calibration_intervals(ci), info=info)
    return FitResult(cal, params, ci, rmse, fit_pct, sse, n, method, tuple(warnings))


def fit_parameters(
    recordings: Sequence[Recording],
    calibration: Calibration,
    robot: RobotProfile,
    free: Sequence[str] = ("A", "B", "C"),
    *,
    x0: Mapping[str, float] | None = None,
    bounds: Mapping[str, tuple[float, float]] | None = None,
    pose_weight: float = 0.0,
    sources: Sequence[str] | None = None,
    max_evaluations: int | None = None,
) -> FitResult:
    """Joint continuous least squares of free parameters on all measured samples.

    Parameters
    ----------
    recordings : sequence of Recording
        Any commands (steps, ramps, turns, mixed); wheel speeds from telemetry or video, empty
        values skipped. The model starts each recording from rest.
    calibration : Calibration
        Values of the parameters that are not free (and effects present).
    robot : RobotProfile
        Geometry for the kinematics.
    free : sequence of str
        Names from :data:`PARAMETER_NAMES` to estimate.
    x0 : Mapping[str, float], optional
        Starting values; parameters without one start from a coarse grid (A, B, C), a scan
        (dead time), the data (top speed, rate limit) or the calibration's value.
    bounds : Mapping[str, (float, float)], optional
        Narrower bounds than :data:`DEFAULT_BOUNDS`.
    pose_weight : float
        Weight of the pose channels ``(x_m, y_m, phi_deg)`` where measured, whose residuals enter
        as wheel-rpm equivalents (see :func:`pose_scale`); 0 fits wheel speeds only.
    sources : sequence of str, optional
        Names of the recordings for the provenance (default: ``recording 1`` ...).
    max_evaluations : int, optional
        At most this many residual evaluations per search and no restarts: a quick refit from
        a start near the optimum (``diagnose``'s held-out folds). Default: converge.

    Returns
    -------
    FitResult

    Raises
    ------
    FitError
        Bad input (see :func:`prepare`), an unknown parameter, or no convergence.
    """
    with one_blas_thread():
        return _fit_parameters(recordings, calibration, robot, free, x0, bounds, pose_weight,
                               sources, max_evaluations)


def _fit_parameters(recordings, calibration, robot, free, x0, bounds, pose_weight, sources,
                    max_evaluations) -> FitResult:
    """:func:`fit_parameters` with OpenBLAS already on one thread."""
    free = list(dict.fromkeys(free))
    if not free:
        raise FitError("no free parameters to fit")
    for n in free:
        check_name(n)
    if not (pose_weight >= 0 and math.isfinite(pose_weight)):
        raise FitError(f"pose_weight must be a finite number >= 0, got {pose_weight!r}")
    data = prepare(recordings, robot, sources)
    lo, hi = checked_bounds(free, bounds)
    # parameters the fitted channels cannot depend on (the gain of a wheel never measured, on
    # wheel speeds alone) stay where they start: searching them only costs evaluations
    held = _unseen(data, free, pose_weight)
    fixed = {n: float(np.clip((x0 or {}).get(n, parameter_value(calibration, n)),
                              lo[free.index(n)], hi[free.index(n)])) for n in held}
    live = [n for n in free if n not in fixed]
    idx = [free.index(n) for n in live]
    base = with_parameters(calibration, fixed)
    pose = fits_pose(data, pose_weight)
    problem = Problem(data, base, robot, live, lo[idx], hi[idx], pose_weight,
                      lazy=not smooth(base, live, pose))
    solve = solver(base, live, pose)
    best = None
    failures = []
    for start in start_points(data, base, robot, live, x0, lo[idx], hi[idx]):
        x_start = np.array([start[n] for n in live])
        budget = max_evaluations or 200 * len(free)
        try:
            sol = solve(problem, x_start, lo[idx], hi[idx], budget)
        except (ValueError, np.linalg.LinAlgError) as err:
            failures.append(f"least squares failed: {err}")
            continue
        if (sol.status < 0 or (sol.status == 0 and max_evaluations is None)
                or not np.isfinite(sol.cost)):
            failures.append(f"least squares did not converge: {sol.message}")
            continue
        if max_evaluations is None:
            sol = restarted(problem, sol, lo[idx], hi[idx], budget, solve)
        if best is None or sol.cost < best.cost:
            best = sol
    if best is None:
        raise FitError(failures[0] if failures else "least squares did not converge")
    r, J_live = problem.fun(best.x), problem.jac(best.x)
    # the held parameters' Jacobian columns are zero: finish reports them not identifiable
    x = np.array([fixed[n] if n in fixed else 0.0 for n in free])
    x[idx] = best.x
    J = np.zeros((J_live.shape[0], len(free)))
    J[:, idx] = J_live
    return finish(data, calibration, robot, free, x, "lsq", J=J, r=r, pose_weight=pose_weight,
                  lower=lo, upper=hi, info_extra={"evaluations": problem.nfev})


def _unseen(data: Sequence[Prepared], free: Sequence[str], pose_weight: float) -> list[str]:
    """Free parameters no fitted residual depends on: with the pose channels unused (no weight
    or no pose measured), a wheel gain of a wheel measured in no recording, and the slip
    efficiencies. Empty when every free parameter would be held (nothing left to fit)."""
    pose = fits_pose(data, pose_weight)
    if pose:
        return []
    seen = np.zeros(4, bool)
    for p in data:
        seen |= p.wheel_mask.any(axis=0)
    out = []
    for n in free:
        m = INDEXED.match(n)
        if m and (m.group(1) == "efficiency" or not seen[int(m.group(2))]):
            out.append(n)
    return out if len(out) < len(free) else []


def fit(
    recordings: Sequence[Recording],
    robot: RobotProfile,
    method: str = "lsq",
    calibration: Calibration | None = None,
    *,
    sources: Sequence[str] | None = None,
    **grid_options,
) -> FitResult:
    """Estimate A, B, C from recordings (``mecanum-hil fit``).

    Parameters
    ----------
    recordings : sequence of Recording
        Recordings with commands and measured wheel speeds.
    robot : RobotProfile
        Geometry for the kinematics.
    method : {"lsq", "paper-grid"}
        Continuous least squares, or the paper's three-pass grid search.
    calibration : Calibration, optional
        Effects to keep fixed during the fit (default: none, the paper's linear model).
    sources : sequence of str, optional
        Names of the recordings for the provenance.
    **grid_options
        For ``paper-grid``: see :func:`mecanum_hil.identify.grid.paper_grid`.

    Returns
    -------
    FitResult
    """
    cal = calibration if calibration is not None else Calibration(source="<fit>")
    if method == "paper-grid":
        # the paper's grid simulates from rest; lsq starts a moving recording in steady state
        for i, rec in enumerate(recordings):
            _require_start_at_rest(rec, robot, source_name(i, rec, sources))
    if method == "lsq":
        if grid_options:
            raise FitError(f"grid options {sorted(grid_options)} apply to --method paper-grid only")
        result = fit_parameters(recordings, cal, robot, sources=sources)
    elif method == "paper-grid":
        from .grid import paper_grid

        data = prepare(recordings, robot, sources)
        res = paper_grid(data, cal, robot, **grid_options)
        x = np.array([res.A, res.B, res.C])
        result = finish(data, cal, robot, list(COEFFICIENTS), x, "paper-grid",
                        extra_warnings=res.warnings, info_extra=res.info)
    else:
        raise FitError(f"unknown method {method!r}; choose lsq or paper-grid")
    if not result.fit_percent > 0.0:
        raise FitError(
            f"the best model explains the data worse than their mean (fit "
            f"{result.fit_percent:.1f} %): no trustworthy coefficients (is there a transient, "
            "and do the commands belong to these wheel speeds?)")
    return result


def _require_start_at_rest(rec: Recording, robot: RobotProfile, src: str) -> None:
    """The model starts every recording from rest: refuse one that starts in motion."""
    wheels = np.asarray(rec.wheel_rpm, dtype=float)
    rows = np.flatnonzero(np.isfinite(wheels).any(axis=1))
    if rows.size == 0 or not np.isfinite(rec.commands).all():
        return  # reported by the engine's own checks
    first = np.nanmax(np.abs(wheels[rows[0]]))
    targets = command_to_wheels(rec.commands[:, 0], rec.commands[:, 1], rec.commands[:, 2],
                                robot.k)
    # a noisy sample at rest is not motion: 2 sigma of 1 rpm of encoder noise is 2 rpm
    from .regimes import noise_sd

    sigma = noise_sd(wheels[rows])
    if first > max(2.0, 0.05 * float(np.abs(targets).max()),
                   4.0 * sigma if np.isfinite(sigma) else 0.0):
        raise FitError(
            f"{src}: starts in motion (a wheel at {first:.1f} rpm at t_s={rec.t_s[rows[0]]:g}); "
            "the paper's grid search starts every recording from rest: use --method lsq "
            "(which starts it in steady state at the measured speeds) or trim the recording "
            "to begin at standstill")
