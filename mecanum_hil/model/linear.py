"""The paper's wheel model (no effects) for many coefficient sets at once, in numpy.

A fit of the paper's model on one short recording evaluates a few thousand coefficient sets on a
start grid and a few dozen during least squares, each over a few hundred samples. Loading numba
to compile the batch simulator costs about 0.6 s of CPU, many times that work; the simulator's
own source run by the interpreter (``mecanum_hil._jit``) loops per robot and sub-step in Python.
Here a few sets (a least-squares step) run as a prefix scan over the time steps, log2(T)
rounds of whole-array arithmetic; many sets (a start grid) run one Python step per sample, each
step updating every coefficient set and every target series at once as numpy arrays. Both
compute the exact zero-order-hold update of :mod:`mecanum_hil.model.motor`,

    [y, z] <- Ad [y, z] + Bd u,

with ``Ad``, ``Bd`` in closed form, vectorised (:func:`zoh_tables`), and the guarded series of
:func:`mecanum_hil.model.discretise.discretise_many` where the closed form loses digits. The
wheel speeds equal the batch simulator's to rounding (tests/model/test_linear.py); there is no
dead time, deadband, gain or drive limit here: callers use it for the paper's model only.

Costs (one core): stepping, about 8 us per time step for a handful of sets, plus
about 10 ns per set and step; the scan, 2-5x less for up to :data:`SCAN_MAX_SERIES` sets x
series (573 steps of 4 sets x 4 wheels: 2.4-2.8 ms against 10-12 ms on a slow day).
:func:`work_units` charges the stepping cost either way (an upper bound) and turns it into the
interpreter's budget
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
    key = np.round(dt * 1e12)  # floats: no int64 overflow for a gap of months
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
    """The same six entries through the augmented matrix's exponential, by Taylor series with
    scaling and squaring, elementwise (as ``mecanum_hil.model.discretise._discretise_series``).

    Of the 4 x 4 augmented matrix ``[[M h, 0, b h], [h, 0, 0, 0], 0]`` only the motor's 2 x 2
    block ``F = M h`` and input column ``b h`` reach these entries (the third state, the
    integral of the speed, feeds nothing back), so the series runs on those as arrays of
    components: terms ``F^n / n!`` and ``F^(n-1) b / n!``, squarings ``E <- E E``,
    ``e <- E e + e``. The scaling is the 4 x 4 matrix's (its norm is that of the first two
    rows); the same sums without the zero products, equal to rounding.
    """
    apb = A + B
    norm = np.maximum(np.abs(apb * h) + np.abs(C * h) + np.abs(A * h), 2.0 * np.abs(h))
    with np.errstate(divide="ignore"):
        squarings = np.maximum(np.ceil(np.log2(np.maximum(norm, 1e-300) / 0.25)), 0).astype(int)
    scale = h / 2.0 ** squarings
    f11, f12, f21 = -apb * scale, C * scale, -scale  # F = [[f11, f12], [f21, 0]]
    g1, g2 = A * scale, scale                        # the input column
    # term n: P = F^n / n! and p = F^(n-1) b / n!, from P = I
    p11, p12, p21, p22 = (np.full_like(scale, v) for v in (1.0, 0.0, 0.0, 1.0))
    e11, e12, e21, e22 = p11.copy(), p12.copy(), p21.copy(), p22.copy()
    e1, e2 = np.zeros_like(scale), np.zeros_like(scale)
    for n in range(1, 19):
        q1, q2 = (p11 * g1 + p12 * g2) / n, (p21 * g1 + p22 * g2) / n
        p11, p12, p21, p22 = ((p11 * f11 + p12 * f21) / n, (p11 * f12) / n,
                              (p21 * f11 + p22 * f21) / n, (p21 * f12) / n)
        e11 += p11
        e12 += p12
        e21 += p21
        e22 += p22
        e1 += q1
        e2 += q2
    for i in range(int(squarings.max(initial=0))):
        k = squarings > i
        a11, a12, a21, a22, b1, b2 = e11[k], e12[k], e21[k], e22[k], e1[k], e2[k]
        e11[k], e12[k] = a11 * a11 + a12 * a21, a11 * a12 + a12 * a22
        e21[k], e22[k] = a21 * a11 + a22 * a21, a21 * a12 + a22 * a22
        e1[k], e2[k] = a11 * b1 + a12 * b2 + b1, a21 * b1 + a22 * b2 + b2
    return np.stack([e11, e12, e21, e22, e1, e2], axis=-1)


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

    Notes
    -----
    Up to :data:`SCAN_MAX_SERIES` sets x series (a least-squares step) run as a prefix scan
    (:func:`_scan`), more (a start grid) step by step (:func:`_stepwise`); both equal the
    batch simulator to rounding.
    """
    u = np.asarray(targets_rpm, dtype=float)
    tab = zoh_tables(coefficients, h_s) if tables is None else tables
    P, (G, T) = tab.shape[0], u.shape
    y = np.zeros((P, G)) if y0_rpm is None else np.broadcast_to(y0_rpm, (P, G)).astype(float)
    z = np.zeros((P, G)) if z0_rpm_s is None else np.broadcast_to(z0_rpm_s, (P, G)).astype(float)
    idx = np.asarray(h_idx, dtype=np.int64)
    if P * G > SCAN_MAX_SERIES:
        return _stepwise(tab, idx, u, y, z)
    out = np.empty((P, G, T))
    start = 0
    while True:  # chunks of SCAN_CHUNK samples bound the scan's memory; each starts in state
        stop = min(start + SCAN_CHUNK, T - 1)
        y1, z1 = _scan(tab, idx[start:stop], u[:, start:stop], y, z)
        out[:, :, start:stop + 1] = y1
        if stop == T - 1:
            return out
        y, z, start = y1[:, :, -1], z1[:, :, -1], stop


#: Sets x series up to which :func:`wheel_speeds` scans: measured (573 samples) 4x
#: faster at 16, even at 64, 2.5x slower at 256 (the scan does log2(T) times the arithmetic).
SCAN_MAX_SERIES = 32
#: Steps per scan: its temporaries are about ten arrays of this x sets x series.
SCAN_CHUNK = 4096


def _stepwise(tab, idx, u, y, z):
    """:func:`wheel_speeds` with one Python step per sample, every set and series at once.

    Each step writes into buffers kept across steps (no temporaries: 2-2.5x faster on 5301
    sets, the same operations in the same order, bit-identical).
    """
    P, (G, T) = tab.shape[0], u.shape
    # per step length: six contiguous (P, 1) columns that broadcast over the series
    rows = [tuple(np.ascontiguousarray(tab[:, k, j:j + 1]) for j in range(6))
            for k in range(tab.shape[1])]
    out = np.empty((T, P, G))
    y, z = np.array(y, dtype=float), np.array(z, dtype=float)
    y_next, z_next, term = np.empty_like(y), np.empty_like(z), np.empty_like(y)
    uniform = len(rows) == 1
    a11, a12, a21, a22, b1, b2 = rows[0]
    for t in range(T - 1):
        out[t] = y
        if not uniform:
            a11, a12, a21, a22, b1, b2 = rows[idx[t]]
        ut = u[:, t]
        # y_next = a11 y + a12 z + b1 u and z_next = a21 y + a22 z + b2 u, left to right
        np.multiply(a11, y, out=y_next)
        y_next += np.multiply(a12, z, out=term)
        y_next += np.multiply(b1, ut, out=term)
        np.multiply(a21, y, out=z_next)
        z_next += np.multiply(a22, z, out=term)
        z_next += np.multiply(b2, ut, out=term)
        y, y_next, z, z_next = y_next, y, z_next, z
    out[T - 1] = y
    return out.transpose(1, 2, 0)


def _scan(tab, idx, u, y0, z0):
    """States ``(y, z)``, shape (P, G, n + 1), after ``n = len(idx)`` steps from ``(y0, z0)``.

    The recursion ``x[t + 1] = M[t] x[t] + b[t] u[t]`` as an inclusive prefix scan
    (Hillis-Steele): in round ``d = 1, 2, 4, ...`` each sample adds the partial sum ``d``
    samples back through the product of the ``d`` step matrices between, and those products
    double alongside. log2(n) rounds of whole-array arithmetic instead of n Python steps; the
    same sums in another order (equal to rounding).
    """
    P, G = y0.shape
    n = idx.size
    step = tab[:, idx, :].transpose(1, 0, 2)  # (n, P, 6): the step into sample t + 1
    ut = u.T[:, None, :]  # (n, 1, G)
    w1 = np.empty((n + 1, P, G))
    w2 = np.empty((n + 1, P, G))
    w1[0], w2[0] = y0, z0
    w1[1:] = step[:, :, 4:5] * ut
    w2[1:] = step[:, :, 5:6] * ut
    # the matrix into each sample, (n + 1, P, 1); row 0 (identity) is never read
    m11, m12, m21, m22 = (np.concatenate([np.full((1, P, 1), float(j in (0, 3))),
                                          step[:, :, j:j + 1]]) for j in range(4))
    d = 1
    while d <= n:
        a1, a2 = w1[:-d], w2[:-d]
        w1[d:], w2[d:] = (w1[d:] + m11[d:] * a1 + m12[d:] * a2,
                          w2[d:] + m21[d:] * a1 + m22[d:] * a2)
        if 2 * d <= n:
            p11, p12, p21, p22 = m11[:-d], m12[:-d], m21[:-d], m22[:-d]
            m11[d:], m12[d:], m21[d:], m22[d:] = (
                m11[d:] * p11 + m12[d:] * p21, m11[d:] * p12 + m12[d:] * p22,
                m21[d:] * p11 + m22[d:] * p21, m21[d:] * p12 + m22[d:] * p22)
        d *= 2
    return w1.transpose(1, 2, 0), w2.transpose(1, 2, 0)
