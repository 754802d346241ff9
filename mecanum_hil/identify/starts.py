"""Where a fit's searches start: a logarithmic grid over the coefficients, a dead-time scan,
and values read off the data.

:func:`start_points` gives the starting points of :func:`mecanum_hil.identify.fit.fit_parameters`:
the values given, else the best local minima of :data:`START_GRID` / :data:`FINE_START_GRID`
(extended by :func:`grid_axis` to what the samples resolve), a scan of the dead time, and
:func:`data_start_values` for the parameters whose "absent" value cannot start a search.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from .._jit import few_threads
from .parameters import COEFFICIENTS, parameter_value, with_parameters
from .prepared import Prepared
from .problem import sse_of

#: Coarse starting grid for the coefficients (log-spaced, covers slow drives to fast micro-motors).
START_GRID: dict[str, tuple[float, ...]] = {
    "A": (0.0, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0, 300.0, 1000.0, 3000.0),
    "B": (0.3, 1.0, 3.0, 10.0, 30.0, 100.0, 300.0),
    "C": (1.0, 10.0, 100.0, 1e3, 1e4, 1e5, 1e6),
}

#: Finer logarithmic grid used when the compiled grid kernel applies (linear model).
FINE_START_GRID: dict[str, np.ndarray] = {
    "A": np.concatenate([[0.0], np.logspace(-1, 3.5, 19)]),
    "B": np.concatenate([[0.0], np.logspace(-1, 3, 13)]),
    "C": np.logspace(0, 6, 19),
}

#: Number of grid minima least squares starts from (the best result is kept), and how far
#: above the best grid point's SSE a further minimum may lie to be used.
START_COUNT = 3
START_SSE_RATIO = 1.25


def data_start_values(data: Sequence[Prepared]) -> dict[str, float]:
    """Starting values of effect parameters whose "absent" value cannot start a search."""
    measured = np.concatenate([p.wheel_rpm[p.wheel_mask] for p in data])
    peak = float(np.max(np.abs(measured)))
    from .regimes import measured_differences

    slopes = []
    for p in data:
        # between consecutive measurements of each wheel (a recorded run's command rows,
        # without one, are skipped)
        d = np.abs(measured_differences(p.wheel_rpm, p.t_s))
        slopes.append(d[np.isfinite(d)])
    slope = float(np.percentile(np.concatenate(slopes), 95)) if any(s.size for s in slopes) else 1.0
    top = max(1.25 * peak, 1.0)
    return {"top_speed_rpm": top, "windup_top_speed_rpm": top,
            "rate_limit_rpm_per_s": max(slope, 1.0)}


def _local_minima(sse: np.ndarray, count: int) -> np.ndarray:
    """Flat indices of up to ``count`` grid points lower than their axis neighbours, best first."""
    is_min = np.isfinite(sse)
    for ax in range(sse.ndim):
        if sse.shape[ax] == 1:
            continue
        pad = [(0, 0)] * sse.ndim
        pad[ax] = (1, 1)
        padded = np.pad(sse, pad, constant_values=np.inf)
        lo = np.take(padded, np.arange(0, sse.shape[ax]), axis=ax)
        hi = np.take(padded, np.arange(2, sse.shape[ax] + 2), axis=ax)
        is_min &= (sse <= lo) & (sse <= hi)
    idx = np.flatnonzero(is_min.ravel())
    if idx.size == 0:
        idx = np.array([int(np.argmin(np.where(np.isfinite(sse), sse, np.inf)))])
    return idx[np.argsort(sse.ravel()[idx], kind="stable")][:count]


def _median_period_s(data: Sequence[Prepared]) -> float:
    """Median period of the wheel measurements [s] (a recorded run's command rows, without
    one, are not samples)."""
    steps = np.concatenate([np.diff(p.t_s[p.wheel_mask.any(axis=1)]) for p in data])
    return float(np.median(steps)) if steps.size else 0.0


def grid_axis(name: str, axis, period_s: float) -> np.ndarray:
    """A start grid axis extended, at its own log spacing, up to the fastest time scale the
    samples resolve: ``A`` and ``B`` up to ``2 / period_s`` [1/s], ``C`` up to its square.
    (The default axes already reach 1000 1/s; a 1 kHz log of a fast motor needs more.)"""
    axis = np.asarray(axis, dtype=float)
    if not period_s > 0 or axis.size < 2 or axis[-2] <= 0:
        return axis
    fastest = 2.0 / period_s
    top = fastest ** 2 if name == "C" else fastest
    ratio = axis[-1] / axis[-2]
    extra = []
    v = axis[-1]
    while v < top and ratio > 1.0 and len(extra) < 20:
        v *= ratio
        extra.append(v)
    return np.concatenate([axis, extra]) if extra else axis


def start_points(data, calibration, robot, free, x0, lower, upper) -> list[dict[str, float]]:
    """Starting points: given values, else the best local minima of a logarithmic grid over the
    free coefficients (the compiled grid kernel for a linear model), a scan for dead time, and
    data-based values for top speed and rate limit."""
    given = dict(x0 or {})
    start = {n: given.get(n, parameter_value(calibration, n)) for n in free}
    missing = [n for n in free if n not in given and not math.isfinite(start[n])]
    if missing:  # read off the data only when needed (a refit gives every start)
        defaults = data_start_values(data)
        for n in missing:
            start[n] = defaults.get(n, 1.0)
    base = with_parameters(calibration, {n: v for n, v in start.items() if n not in COEFFICIENTS})
    grid_names = [n for n in COEFFICIENTS if n in free and n not in given]
    starts = [dict(start)]
    if grid_names:
        linear = not base.effects.nonlinear
        spec = FINE_START_GRID if linear else START_GRID
        period = _median_period_s(data)
        axes = [grid_axis(n, spec[n], period) if n in grid_names else
                np.asarray((getattr(base, n),), dtype=float) for n in COEFFICIENTS]
        pts = np.array(np.meshgrid(*axes, indexing="ij")).reshape(3, -1).T
        ok = (pts[:, 0] + pts[:, 1] > 0) & (pts[:, 2] > 0)
        sse = np.full(pts.shape[0], np.inf)
        if linear:
            from .grid import evaluate_points, grid_data

            g = grid_data(data, base, robot)
            with few_threads(pts.shape[0] * g.target_rpm.size):
                sse[ok] = evaluate_points(g, pts[ok])
        else:
            sse[ok] = sse_of(data, [base.with_coefficients(*pt) for pt in pts[ok]], robot)
        starts = []
        minima = _local_minima(sse.reshape([a.size for a in axes]), START_COUNT)
        # a minimum far above the best rarely leads least squares to a better optimum
        minima = [f for f in minima if sse[f] <= START_SSE_RATIO * sse[minima[0]]]
        for flat in minima:
            s = dict(start)
            for i, n in enumerate(COEFFICIENTS):
                if n in grid_names:
                    s[n] = float(pts[flat, i])
            starts.append(s)
    if "dead_time_s" in free and "dead_time_s" not in given:
        base = with_parameters(base, {n: starts[0][n] for n in COEFFICIENTS if n in free})
        span = min(float(np.median([p.t_s[-1] - p.t_s[0] for p in data])) / 4.0, 0.5)
        # a coarse scan of the span, and every sample period up to 20 samples (a fast drive's
        # dead time is a few samples, finer than the coarse scan)
        period = _median_period_s(data)
        cands = np.unique(np.concatenate([[start["dead_time_s"]], np.linspace(0.0, span, 26),
                                          np.arange(0.0, min(span, 20.0 * period), period)]))
        calibs = [with_parameters(base, {"dead_time_s": c}) for c in cands]
        best = float(cands[int(np.argmin(sse_of(data, calibs, robot)))])
        for s in starts:
            s["dead_time_s"] = best
    return [{n: float(np.clip(s[n], lower[i], upper[i])) for i, n in enumerate(free)}
            for s in starts]
