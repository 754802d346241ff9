"""The paper's wheel model (no effects) for many coefficient sets at once, in numpy.

A fit of the paper's model on one short recording evaluates a few thousand coefficient sets on a
start grid and a few dozen during least squares, each over a few hundred samples. Loading numba
to compile the batch simulator costs about 0.6 s of CPU, many times that work; the simulator's
own source run by the interpreter (``mecanum_hil._jit``) loops per robot and sub-step in Python.
Here one Python loop runs over the time steps, and each step updates every coefficient set and
every target series at once as numpy arrays: the exact zero-order-hold update of
:mod:`mecanum_hil.model.motor`,

    [y, z] <- Ad [y, z] + Bd u,

with ``Ad``, ``Bd`` in closed form, vectorised (:func:`zoh_tables`), and the guarded series of
:func:`mecanum_hil.model.discretise.discretise_many` where the closed form loses digits. The
wheel speeds equal the batch simulator's to rounding (tests/model/test_linear.py); there is no
dead time, deadband, gain or drive limit here: callers use it for the paper's model only.

Costs (2026-11-23, one core): about 8 us per time step for a handful of sets, plus about 10 ns
per set and step; :func:`work_units` turns that into the interpreter's budget
(:data:`mecanum_hil._jit.INTERPRETED_BUDGET`) so that a process that would spend more switches
to compiled code.
"""

from __future__ import annotations

import math

import numpy as np

#: Rough cost of one time step [us], of each set x series on it [us], and of one table row
#: (one set at one distinct step length, complex arithmetic) [us] (see the module text).
_STEP_US = 8.0
_ELEMENT_US = 0.01
_TABLE_US = 1.2
#: What one unit of the interpreter's budget costs [us] (a robot-step of the simulator's source).
_UNIT_US = 25.0


def work_units(steps: int, sets: int, tables: int = 0) -> int:
    """The interpreter budget a job uses: ``steps`` time steps over ``sets`` sets x series,
    and ``tables`` rows of :func:`zoh_tables` (sets x distinct step lengths)."""
    return math.ceil((steps * (_STEP_US + _ELEMENT_US * sets) + _TABLE_US * tables) / _UNIT_US)


def step_lengths(t_s) -> tuple[np.ndarray, np.ndarray]:
    """Distinct step lengths [s] of a time grid and each step's row among them; lengths equal
    to rounding (1e-12 s) share a row, as in the batch simulator."""
    dt = np.diff(np.asarray(t_s, dtype=float))
    key = np.round(dt * 1e12).astype(np.int64)
    _, first, idx = np.unique(key, return_index=True, return_inverse=True)
    return dt[first], idx.reshape(-1)


def _well_conditioned(A, B, C, h):
    # the rule of mecanum_hil.model.discretise.discretise_step, elementwise
    apb = A + B
    ch2 = C * h * h
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(A > 0.0, apb / np.where(A > 0.0, A, 1.0), np.inf)
    return ((apb * h <= 40.0) & (ch2 <= 400.0) & (A > 0.0)
            & (ch2 >= 1e-4 * np.maximum(1.0, apb * h) * np.maximum(1.0, ratio)))


def _closed_form(A, B, C, h):
    """``(a11, a12, a21, a22, b1, b2)`` of the exact update in closed form, elementwise (as
    ``mecanum_hil.model.discretise._discretise_closed``: exp(M h) = e^{s h} (c I + g (M - s I)),
    with ``c = cosh(d h)``, ``g = sinh(d h) / d`` through complex ``d`` for ringing roots)."""
    apb = A + B
    s = -0.5 * apb
    d2 = s * s - C
    x = d2 * h * h
    series = np.abs(x) < 1e-4
    d = np.sqrt(np.where(series, 1.0, d2).astype(complex))
    c = np.where(series, 1.0 + x / 2.0 * (1.0 + x / 12.0 * (1.0 + x / 30.0)),
                 np.cosh(d * h).real)
    g = np.where(series, h * (1.0 + x / 6.0 * (1.0 + x / 20.0 * (1.0 + x / 42.0))),
                 (np.sinh(d * h) / d).real)
    es = np.exp(s * h)
    a11 = es * (c + g * (-apb - s))
    a12 = es * g * C
    a21 = -es * g
    a22 = es * (c - g * s)
    p21 = (a11 - 1.0 - apb * a21) / C
    p22 = (a12 - apb * (a22 - 1.0)) / C
    return np.stack([a11, a12, a21, a22, -a21 * A - (a22 - 1.0), p21 * A + p22], axis=-1)


def zoh_tables(coefficients, h_s) -> np.ndarray:
    """``(a11, a12, a21, a22, b1, b2)`` of the exact update for each set and step length.

    Parameters
    ----------
    coefficients : array_like, shape (P, 3)
        ``(A [1/s], B [1/s], C [1/s^2])`` rows; ``A, B >= 0``, ``A + B > 0``, ``C > 0``.
    h_s : array_like, shape (K,)
        Step lengths [s].

    Returns
    -------
    ndarray, shape (P, K, 6)
    """
    co = np.asarray(coefficients, dtype=float).reshape(-1, 3)
    h = np.asarray(h_s, dtype=float).reshape(1, -1)
    A, B, C = (co[:, i:i + 1] for i in range(3))
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        out = _closed_form(A, B, C, h)
    bad = ~_well_conditioned(A, B, C, h) | ~np.isfinite(out).all(axis=-1)
    if bad.any():
        Ab, Bb, Cb, hb = (np.broadcast_to(v, bad.shape)[bad] for v in (A, B, C, h))
        out[bad] = _series(Ab, Bb, Cb, hb)
    return out


def _series(A, B, C, h):
    """The same six entries through the 4 x 4 augmented matrix's exponential, by Taylor series
    with scaling and squaring, elementwise (as ``mecanum_hil.model.discretise._expm4``)."""
    m = np.zeros((A.size, 4, 4))
    m[:, 0, 0] = -(A + B) * h
    m[:, 0, 1] = C * h
    m[:, 0, 3] = A * h
    m[:, 1, 0] = -h
    m[:, 1, 3] = h
    m[:, 2, 0] = h
    norm = np.abs(m).sum(axis=2).max(axis=1)
    with np.errstate(divide="ignore"):
        squarings = np.maximum(np.ceil(np.log2(np.maximum(norm, 1e-300) / 0.25)), 0).astype(int)
    a = m / (2.0 ** squarings)[:, None, None]
    e = np.broadcast_to(np.eye(4), m.shape).copy()
    term = e.copy()
    for n in range(1, 19):
        term = term @ a / n
        e += term
    for i in range(int(squarings.max(initial=0))):
        more = squarings > i
        e[more] = e[more] @ e[more]
    return np.stack([e[:, 0, 0], e[:, 0, 1], e[:, 1, 0], e[:, 1, 1], e[:, 0, 3], e[:, 1, 3]],
                    axis=-1)


def wheel_speeds(coefficients, h_s, h_idx, targets_rpm, y0_rpm=None, z0_rpm_s=None, *,
                 tables=None):
    """Wheel speeds of the paper's model at every sample, for every set and target series.

    Parameters
    ----------
    coefficients : array_like, shape (P, 3)
        ``(A, B, C)`` rows [1/s], [1/s], [1/s^2].
    h_s : array_like, shape (K,)
        Distinct step lengths [s].
    h_idx : array_like of int, shape (T - 1,)
        Row of ``h_s`` for the step after each sample.
    targets_rpm : array_like, shape (G, T)
        Target series [rpm]: the target at sample ``t`` is held until sample ``t + 1``.
    y0_rpm, z0_rpm_s : array_like, shape (P, G) or (G,), optional
        Speed [rpm] and integral of the speed error [rpm s] at the first sample (default rest).

    tables : ndarray, shape (P, K, 6), optional
        :func:`zoh_tables` of ``coefficients`` and ``h_s``, when the caller has them.

    Returns
    -------
    ndarray, shape (P, G, T)
        Wheel speed at each sample [rpm] (the state before the sample's target acts).
    """
    u = np.asarray(targets_rpm, dtype=float)
    tab = zoh_tables(coefficients, h_s) if tables is None else tables
    P, (G, T) = tab.shape[0], u.shape
    # per step length: six (P, 1) columns that broadcast over the series
    rows = [tuple(tab[:, k, j:j + 1] for j in range(6)) for k in range(tab.shape[1])]
    y = np.zeros((P, G)) if y0_rpm is None else np.broadcast_to(y0_rpm, (P, G)).astype(float)
    z = np.zeros((P, G)) if z0_rpm_s is None else np.broadcast_to(z0_rpm_s, (P, G)).astype(float)
    out = np.empty((T, P, G))
    idx = np.asarray(h_idx, dtype=np.int64)
    uniform = len(rows) == 1
    a11, a12, a21, a22, b1, b2 = rows[0]
    for t in range(T - 1):
        out[t] = y
        if not uniform:
            a11, a12, a21, a22, b1, b2 = rows[idx[t]]
        ut = u[:, t]
        y, z = a11 * y + a12 * z + b1 * ut, a21 * y + a22 * z + b2 * ut
    out[T - 1] = y
    return out.transpose(1, 2, 0)
