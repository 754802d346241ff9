"""The paper's grid search for A, B, C, exact and fast (compiled, grid rows in parallel).

Nakagawa et al. fix B = 15.5, search A and C over 0..2000 in steps of 1, sweep B over
5.5..25.5 in steps of 0.1 with A and C fixed, and search A and C again, each pass minimising the
sum of squared wheel-speed errors (SSE). :func:`paper_grid` does exactly that, with the grids
configurable, and returns in each pass exactly the argmin an exhaustive evaluation of the pass's
grid gives:

* Ties (equal SSE) go to the smallest grid index, A before B before C, i.e. the smallest A, then
  the smallest B, then the smallest C.
* Grid points that are not a stable model of the paper's form (``C <= 0`` -- the paper's grid
  starts at C = 0, where the integrator drops out and a calibration would be refused -- or
  ``A + B <= 0``, or a negative or non-finite value) are excluded: their SSE is +inf and they are
  never chosen.

Each grid point's SSE is computed with the exact zero-order-hold discretisation of the wheel
model in closed form (the 2x2 matrix exponential through the characteristic roots; a Taylor
series where the roots nearly coincide), over every measured wheel sample of every recording.
Wheels that share a target series are simulated once: their SSE is
``sum_t c_t (y_t - mean_t)^2 + scatter`` with ``c_t`` the number of measured wheels at sample t,
``mean_t`` their mean and ``scatter`` their spread about it, which does not depend on the model.
Each row of the grid (one A, one B, all C) stops summing a point's squared errors once the partial
sum exceeds the row's best so far: squared errors are non-negative and a floating-point sum of
non-negative terms never decreases, so this cannot change the argmin.

Effects: ``deadband``, ``wheel_gain`` and ``dead_time`` (exact, on the refined time grid the
simulator uses) are applied to the targets; ``saturation`` and ``rate_limit`` make the model
nonlinear and are refused here (use ``lsq``); ``slip`` does not act on wheel speeds.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._jit import njit, prange
from ..errors import FitError
from ..model.calibration import Calibration
from ..model.kinematics import command_to_wheels
from ..model.robot import RobotProfile
from ..model.simulate import _delay_grid

#: The paper's grids as (first, last, step).
PAPER_A_GRID = (0.0, 2000.0, 1.0)
PAPER_B_GRID = (5.5, 25.5, 0.1)
PAPER_C_GRID = (0.0, 2000.0, 1.0)
PAPER_B_START = 15.5


def axis(spec: tuple[float, float, float] | Sequence[float]) -> np.ndarray:
    """Grid values from ``(first, last, step)`` (inclusive), free of accumulated rounding.

    ``first + k step`` is rounded to 12 significant decimals so that 5.5 + 100 x 0.1 is 15.5.
    """
    if len(spec) != 3:
        raise FitError(f"a grid is (first, last, step), got {spec!r}")
    lo, hi, step = (float(v) for v in spec)
    if not all(map(math.isfinite, (lo, hi, step))) or step <= 0 or hi < lo:
        raise FitError(f"bad grid {lo:g}:{hi:g}:{step:g} (need first <= last and step > 0)")
    n = math.floor((hi - lo) / step + 1e-9) + 1
    if n > 10_000_000:
        raise FitError(f"grid {lo:g}:{hi:g}:{step:g} has {n} values; too many")
    return np.round(lo + step * np.arange(n), 12)


@dataclass(frozen=True)
class GridData:
    """Recordings flattened for the kernels: one segment per recording and target series.

    Attributes
    ----------
    h_s : (K,) float64
        Distinct step lengths [s].
    seg_start : (S + 1,) int64
        Segment ``s`` occupies entries ``seg_start[s]:seg_start[s + 1]``.
    h_idx : (M,) int64
        Row of ``h_s`` for the step after each entry (unused at a segment's last entry).
    target_rpm : (M,) float64
        Wheel target in force from each entry to the next [rpm].
    weight : (M,) float64
        Number of measured wheel samples at the entry (0 between samples on a refined grid).
    mean_rpm : (M,) float64
        Their mean [rpm].
    scatter : float
        Sum of squared deviations of the measured wheels from ``mean_rpm`` [rpm^2].
    """

    h_s: np.ndarray
    seg_start: np.ndarray
    h_idx: np.ndarray
    target_rpm: np.ndarray
    weight: np.ndarray
    mean_rpm: np.ndarray
    scatter: float


def grid_data(data, calibration: Calibration, robot: RobotProfile) -> GridData:
    """Flatten prepared recordings (:func:`mecanum_hil.identify.fit.prepare`) for the kernels."""
    eff = calibration.effects
    if eff.nonlinear:
        raise FitError("the grid search needs a linear model: the calibration has a saturation or "
                       "rate_limit effect; use --method lsq")
    keys: dict[int, int] = {}
    h_list: list[float] = []
    seg_start = [0]
    h_idx, target, weight, mean = [], [], [], []
    scatter = 0.0
    for p in data:
        t = p.t_s
        cmd = p.commands[None]
        if eff.dead_time_s > 0:
            grid, cmd, record = _delay_grid(t, cmd, float(eff.dead_time_s), np.zeros((1, 3)))
            sample_idx = np.flatnonzero(record >= 0)  # the samples' places on the grid
        else:
            grid, sample_idx = t, np.arange(t.size)
        c = cmd[0]
        wheels = command_to_wheels(c[:, 0], c[:, 1], c[:, 2], robot.k)
        wheels = np.where(np.abs(wheels) < eff.deadband_rpm, 0.0, wheels) * np.array(eff.gains)
        dt = np.diff(grid)
        step_rows = np.zeros(grid.size, np.int64)
        for j, k in enumerate(np.round(dt * 1e12)):  # floats: no overflow for a long gap
            if k not in keys:
                keys[int(k)] = len(h_list)
                h_list.append(float(dt[j]))
            step_rows[j] = keys[int(k)]
        groups: dict[bytes, list[int]] = {}
        for i in range(4):
            if p.wheel_mask[:, i].any():
                groups.setdefault(np.ascontiguousarray(wheels[:, i]).tobytes(), []).append(i)
        for members in groups.values():
            meas = p.wheel_rpm[:, members]
            mask = p.wheel_mask[:, members]
            cnt = mask.sum(axis=1).astype(float)
            tot = np.where(mask, meas, 0.0).sum(axis=1)
            mu = np.divide(tot, cnt, out=np.zeros_like(tot), where=cnt > 0)
            scatter += float(np.sum(np.where(mask, (meas - mu[:, None]) ** 2, 0.0)))
            w = np.zeros(grid.size)
            m = np.zeros(grid.size)
            w[sample_idx] = cnt
            m[sample_idx] = mu
            h_idx.append(step_rows)
            target.append(wheels[:, members[0]])
            weight.append(w)
            mean.append(m)
            seg_start.append(seg_start[-1] + grid.size)
    if len(seg_start) == 1:
        raise FitError("no measured wheel speed in the recordings")
    return GridData(np.array(h_list if h_list else [1.0]), np.array(seg_start, np.int64),
                    np.concatenate(h_idx), np.concatenate(target), np.concatenate(weight),
                    np.concatenate(mean), scatter)


@njit(cache=True, inline="always")
def _admissible(A, B, C):
    return (math.isfinite(A) and math.isfinite(B) and math.isfinite(C) and A >= 0.0
            and B >= 0.0 and C > 0.0 and A + B > 0.0)


@njit(cache=True)
def discretise_closed_form(A, B, C, h):
    """Exact ZOH update ``[y, z] <- Ad [y, z] + Bd u`` of the wheel model in closed form.

    Returns ``(a11, a12, a21, a22, b1, b2)`` for ``M = [[-(A + B), C], [-1, 0]]``,
    ``b = [A, 1]``: ``Ad = exp(M h)``, ``Bd = M^-1 (Ad - I) b`` (needs ``C > 0``).
    """
    s = -0.5 * (A + B)
    D = s * s - C
    x = D * h * h
    es = math.exp(s * h)
    if abs(x) <= 1e-2:
        # nearly repeated roots: cosh(r h) and sinh(r h) / r as series in x = r^2 h^2
        ch = 1.0 + x / 2.0 * (1.0 + x / 12.0 * (1.0 + x / 30.0 * (1.0 + x / 56.0)))
        sh = h * (1.0 + x / 6.0 * (1.0 + x / 20.0 * (1.0 + x / 42.0 * (1.0 + x / 72.0))))
        p = es * ch
        q = es * sh
        e11 = p + q * (-(A + B) - s)
        e12 = q * C
        e21 = -q
        e22 = p - q * s
    elif x < 0.0:
        w = math.sqrt(-D)
        p = es * math.cos(w * h)
        q = es * math.sin(w * h) / w
        e11 = p + q * (-(A + B) - s)
        e12 = q * C
        e21 = -q
        e22 = p - q * s
    else:
        # distinct real roots; the small one as C / l2 avoids cancellation in s + sqrt(D)
        l2 = s - math.sqrt(D)
        l1 = C / l2
        g1 = math.exp(l1 * h)
        g2 = math.exp(l2 * h)
        inv = 1.0 / (l1 - l2)
        # exp(M h) = (g1 (M - l2 I) - g2 (M - l1 I)) / (l1 - l2)
        e11 = (g1 * (-(A + B) - l2) - g2 * (-(A + B) - l1)) * inv
        e12 = (g1 - g2) * C * inv
        e21 = -(g1 - g2) * inv
        e22 = (g1 * (-l2) - g2 * (-l1)) * inv
    v1 = (e11 - 1.0) * A + e12
    v2 = e21 * A + (e22 - 1.0)
    return e11, e12, e21, e22, -v2, (v1 - (A + B) * v2) / C


@njit(cache=True)
def _sse(A, B, C, h_s, seg_start, h_idx, target, weight, mean, bound, tab, done, pid):
    """Model-dependent part of the SSE of one point; stops early once above ``bound``.

    ``tab`` rows (one discretisation per step length) are computed when a step first needs
    them, marked in ``done`` with the point's id ``pid``: a recording timed by a host has
    hundreds of step lengths, and a sum that stops early needs few of them. A wheel at rest
    with a zero target stays exactly at rest, so such steps need none.
    """
    if not _admissible(A, B, C):
        return np.inf
    total = 0.0
    if h_s.size == 1:
        # uniform sampling (the usual case): the update in registers
        a11, a12, a21, a22, b1, b2 = discretise_closed_form(A, B, C, h_s[0])
        for s in range(seg_start.size - 1):
            y = 0.0
            z = 0.0
            for j in range(seg_start[s], seg_start[s + 1]):
                e = y - mean[j]
                total += weight[j] * e * e
                if total > bound:
                    return total
                u = target[j]
                y, z = a11 * y + a12 * z + b1 * u, a21 * y + a22 * z + b2 * u
        return total
    for s in range(seg_start.size - 1):
        y = 0.0
        z = 0.0
        for j in range(seg_start[s], seg_start[s + 1]):
            e = y - mean[j]
            total += weight[j] * e * e
            if total > bound:
                return total
            u = target[j]
            if u == 0.0 and y == 0.0 and z == 0.0:
                continue  # the update gives zeros again, whatever the step
            r = h_idx[j]
            if done[r] != pid:
                d = discretise_closed_form(A, B, C, h_s[r])
                for k in range(6):
                    tab[r, k] = d[k]
                done[r] = pid
            y, z = (tab[r, 0] * y + tab[r, 1] * z + tab[r, 4] * u,
                    tab[r, 2] * y + tab[r, 3] * z + tab[r, 5] * u)
    return total


@njit(cache=True, parallel=True)
def sse_points(points, h_s, seg_start, h_idx, target, weight, mean):
    """Model-dependent SSE of each point ``(A, B, C)`` (rows of ``points``), in full."""
    n = points.shape[0]
    out = np.empty(n)
    for i in prange(n):
        tab = np.empty((h_s.size, 6))
        done = np.full(h_s.size, -1, np.int64)
        out[i] = _sse(points[i, 0], points[i, 1], points[i, 2], h_s, seg_start, h_idx, target,
                      weight, mean, np.inf, tab, done, 0)
    return out


@njit(cache=True, parallel=True)
def grid_rows(a_values, b_values, c_values, bound, h_s, seg_start, h_idx, target, weight, mean):
    """Best C of each (A, B) row of the product grid: its SSE (model part) and index.

    Within a row the first (smallest-index) point of the least SSE wins. ``bound`` is the SSE
    of some point of the grid: a point's sum stops once it exceeds ``min(bound, row best)``, and
    a row none of whose points reaches ``bound`` reports a partial sum above ``bound`` (it cannot
    hold the grid's argmin). The index is -1 when no point of the row is admissible.
    """
    na = a_values.size
    nb = b_values.size
    best = np.full(na * nb, np.inf)
    best_idx = np.full(na * nb, -1, np.int64)
    for row in prange(na * nb):
        A = a_values[row // nb]
        B = b_values[row % nb]
        tab = np.empty((h_s.size, 6))
        done = np.full(h_s.size, -1, np.int64)
        b_sse = np.inf
        b_i = -1
        for ic in range(c_values.size):
            v = _sse(A, B, c_values[ic], h_s, seg_start, h_idx, target, weight, mean,
                     min(bound, b_sse), tab, done, ic)
            if v < b_sse:
                b_sse = v
                b_i = ic
        best[row] = b_sse
        best_idx[row] = b_i
    return best, best_idx


def _args(g: GridData):
    return (g.h_s, g.seg_start, g.h_idx, g.target_rpm, g.weight, g.mean_rpm)


def evaluate_points(g: GridData, points) -> np.ndarray:
    """SSE [rpm^2] of each ``(A, B, C)`` row of ``points`` (+inf where not admissible).

    A small job (a fit's start grid on a short recording) runs in numpy
    (:mod:`mecanum_hil.model.linear`, equal to rounding) while numba is not loaded.
    """
    from .._jit import interpret
    from ..model.linear import work_units

    pts = np.ascontiguousarray(np.asarray(points, dtype=float).reshape(-1, 3))
    if interpret(work_units(g.target_rpm.size, pts.shape[0], pts.shape[0] * g.h_s.size)):
        return _sse_numpy(g, pts) + g.scatter
    return sse_points(pts, *_args(g)) + g.scatter


def _sse_numpy(g: GridData, pts: np.ndarray) -> np.ndarray:
    """:func:`sse_points` through :func:`mecanum_hil.model.linear.wheel_speeds`."""
    from ..model.linear import wheel_speeds, zoh_tables

    A, B, C = pts.T
    ok = (np.isfinite(pts).all(axis=1) & (A >= 0.0) & (B >= 0.0) & (C > 0.0) & (A + B > 0.0))
    sse = np.full(pts.shape[0], np.inf)
    total = np.zeros(int(ok.sum()))
    tables = zoh_tables(pts[ok], g.h_s)  # once for every segment
    for s in range(g.seg_start.size - 1):
        lo, hi = g.seg_start[s], g.seg_start[s + 1]
        y = wheel_speeds(pts[ok], g.h_s, g.h_idx[lo:hi - 1], g.target_rpm[None, lo:hi],
                         tables=tables)[:, 0]
        total += ((y - g.mean_rpm[lo:hi]) ** 2) @ g.weight[lo:hi]
    sse[ok] = total
    return sse


def grid_argmin(g: GridData, a_values, b_values, c_values) -> tuple[float, float, float, float]:
    """Exact argmin of the SSE over the product grid: ``(A, B, C, SSE [rpm^2])``.

    Ties go to the smallest A index, then B, then C (see the module docstring).
    """
    a = np.ascontiguousarray(np.asarray(a_values, dtype=float).ravel())
    b = np.ascontiguousarray(np.asarray(b_values, dtype=float).ravel())
    c = np.ascontiguousarray(np.asarray(c_values, dtype=float).ravel())
    # a bound from a strided sub-grid (points of this grid) lets most sums stop early
    sa = max(1, a.size // 64)
    sb = max(1, b.size // 64)
    sc = max(1, c.size // 64)
    sub = np.array(np.meshgrid(a[::sa], b[::sb], c[::sc], indexing="ij")).reshape(3, -1).T
    sse = sse_points(np.ascontiguousarray(sub), *_args(g))
    bound = float(np.min(sse))
    if np.isfinite(bound):
        # and from every point of the grid around the sub-grid's best: near the minimum
        ia, ib, ic = np.unravel_index(int(np.argmin(sse)), (a[::sa].size, b[::sb].size,
                                                              c[::sc].size))
        near = [v[max(0, i * st - st):i * st + st + 1]
                for v, i, st in ((a, ia, sa), (b, ib, sb), (c, ic, sc))]
        win = np.array(np.meshgrid(*near, indexing="ij")).reshape(3, -1).T
        bound = min(bound, float(np.min(sse_points(np.ascontiguousarray(win), *_args(g)))))
    best, idx = grid_rows(a, b, c, bound, *_args(g))
    row = int(np.argmin(best))  # first occurrence: smallest A, then B
    if not np.isfinite(best[row]) or idx[row] < 0:
        raise FitError("no grid point is a stable model (need A + B > 0 and C > 0)")
    return (float(a[row // b.size]), float(b[row % b.size]), float(c[idx[row]]),
            float(best[row] + g.scatter))


@dataclass(frozen=True)
class GridResult:
    """Outcome of :func:`paper_grid`: the final point, each pass's point, and notes."""

    A: float
    B: float
    C: float
    sse: float
    passes: tuple[tuple[float, float, float, float], ...]
    warnings: tuple[str, ...] = ()
    info: dict[str, Any] = field(default_factory=dict)


def _spec_text(spec) -> str:
    return ":".join(f"{float(v):g}" for v in spec)


def paper_grid(data, calibration: Calibration, robot: RobotProfile, *,
               a_grid=PAPER_A_GRID, b_grid=PAPER_B_GRID, c_grid=PAPER_C_GRID,
               b_start: float = PAPER_B_START) -> GridResult:
    """The paper's three-pass grid search.

    Parameters
    ----------
    data : list
        Prepared recordings (:func:`mecanum_hil.identify.fit.prepare`).
    calibration : Calibration
        Effects held fixed (linear ones only, see the module docstring).
    robot : RobotProfile
        Geometry for the kinematics.
    a_grid, b_grid, c_grid : (first, last, step)
        Grids of A [1/s], B [1/s] and C [1/s^2]; default the paper's.
    b_start : float
        B held during the first pass [1/s]; default the paper's 15.5.

    Returns
    -------
    GridResult
    """
    g = grid_data(data, calibration, robot)
    a, b, c = axis(a_grid), axis(b_grid), axis(c_grid)
    p1 = grid_argmin(g, a, [float(b_start)], c)
    p2 = grid_argmin(g, [p1[0]], b, [p1[2]])
    p3 = grid_argmin(g, a, [p2[1]], c)
    warnings = []
    for name, value, values in (("A", p3[0], a), ("B", p3[1], b), ("C", p3[2], c)):
        if values.size > 1 and (value == values[-1] or (value == values[0] and values[0] > 0)):
            warnings.append(f"{name} = {value:g} is on the edge of its grid "
                            f"{values[0]:g}..{values[-1]:g}; the optimum may lie outside")
    info = {"grid_a": _spec_text(a_grid), "grid_b": _spec_text(b_grid),
            "grid_c": _spec_text(c_grid), "grid_b_start": float(b_start),
            "grid_points": int(2 * a.size * c.size + b.size)}
    return GridResult(p3[0], p3[1], p3[2], p3[3], (p1, p2, p3), tuple(warnings), info)
