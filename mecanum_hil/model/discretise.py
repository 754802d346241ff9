"""The wheel model discretised over one step, in compiled code (pure).

:func:`discretise_step` gives the zero-order-hold table of
:func:`mecanum_hil.model.motor.discretise`
for one coefficient set and step length (a guarded closed form, else a series), and
:func:`discretise_many` for many sets at once. The batch simulator's kernel
(``model/_kernels.py``), the stepper (``model/stepper.py``) and the shadow monitor's kernel
(``monitor/_kernel.py``) all use it; it lives apart from them so that none needs another to have
it. Compiled by numba when first called compiled (``mecanum_hil._jit``).
"""

from __future__ import annotations

import math

import numpy as np

from .._jit import njit, pick
from .motor import TABLE_WIDTH


@njit(cache=True)
def _discretise_closed(A, B, C, h, out):
    """Closed-form exact discretisation of one wheel over ``h`` seconds into ``out[:10]``.

    Same layout as :func:`mecanum_hil.model.motor.discretise` (without the trailing ``h``):
    ``a11 a12 a21 a22 b1 b2 cq1 cq2 dq exp(-B h)``.
    """
    apb = A + B
    s = -0.5 * apb  # half the trace of M = [[-(A+B), C], [-1, 0]]
    d2 = s * s - C
    x = d2 * h * h
    if abs(x) < 1e-4:
        # series of cosh/cos and sinh/sin over d: smooth through the repeated-pole case
        c = 1.0 + x / 2.0 * (1.0 + x / 12.0 * (1.0 + x / 30.0))
        g = h * (1.0 + x / 6.0 * (1.0 + x / 20.0 * (1.0 + x / 42.0)))
    elif d2 > 0:
        d = math.sqrt(d2)
        c = math.cosh(d * h)
        g = math.sinh(d * h) / d
    else:
        w = math.sqrt(-d2)
        c = math.cos(w * h)
        g = math.sin(w * h) / w
    es = math.exp(s * h)
    # exp(M h) = e^{s h} (c I + g (M - s I))
    a11 = es * (c + g * (-apb - s))
    a12 = es * g * C
    a21 = -es * g
    a22 = es * (c - g * s)
    # P1 = M^-1 (Ad - I), P2 = M^-1 (P1 - h I), M^-1 = [[0, -1], [1/C, -(A+B)/C]]
    d11 = a11 - 1.0
    d22 = a22 - 1.0
    p11 = -a21
    p12 = -d22
    p21 = (d11 - apb * a21) / C
    p22 = (a12 - apb * d22) / C
    q11 = -p21
    q12 = -(p22 - h)
    out[0] = a11
    out[1] = a12
    out[2] = a21
    out[3] = a22
    out[4] = p11 * A + p12
    out[5] = p21 * A + p22
    out[6] = p11
    out[7] = p12
    out[8] = q11 * A + q12
    out[9] = math.exp(-B * h)



@njit(cache=True)
def _discretise_series(A, B, C, h, out):
    """The exponential of the augmented matrix ``m`` (below) by scaling and squaring with a
    Taylor series, in scalars: ``||m / 2^s|| <= 1/4``, 18 terms leave a truncation error far
    below rounding.

    ``m = [[-(A+B) h, C h, 0, A h], [-h, 0, 0, h], [h, 0, 0, 0], [0, 0, 0, 0]]`` (speed,
    integral of the error, integral of the speed; the input). Its powers keep column 2 and row
    3 zero, so a term needs only rows 0-2 of columns 0, 1, 3 from rows 0-1 of the one before:
    15 products a term instead of a 4 x 4 matrix product (which numba sends to BLAS, with a
    new array each time: ~5 us a call on a slow day, against ~0.1 us here; the same sums
    without the zero products, equal to rounding).
    """
    apb = A + B
    norm = max(abs(apb * h) + abs(C * h) + abs(A * h), abs(h) + abs(h), abs(h))
    s = 0
    while norm > 0.25:
        norm *= 0.5
        s += 1
    k = 1.0 / (2.0 ** s)
    a00, a01, a03 = -apb * h * k, C * h * k, A * h * k
    a10, a13 = -h * k, h * k
    a20 = h * k
    # e = I + term (n = 1: term = a); rows 0-2, columns 0, 1, 3
    t00, t01, t03 = a00, a01, a03
    t10, t11, t13 = a10, 0.0, a13
    t20, t21, t23 = a20, 0.0, 0.0
    e00, e01, e03 = 1.0 + t00, t01, t03
    e10, e11, e13 = t10, 1.0 + t11, t13
    e20, e21, e23 = t20, t21, t23
    for n in range(2, 19):
        # term <- term a / n (columns of a: 0 = (a00, a10), 1 = (a01, 0), 3 = (a03, a13))
        t00, t01, t03 = ((t00 * a00 + t01 * a10) / n, (t00 * a01) / n,
                         (t00 * a03 + t01 * a13) / n)
        t10, t11, t13 = ((t10 * a00 + t11 * a10) / n, (t10 * a01) / n,
                         (t10 * a03 + t11 * a13) / n)
        t20, t21, t23 = ((t20 * a00 + t21 * a10) / n, (t20 * a01) / n,
                         (t20 * a03 + t21 * a13) / n)
        e00 += t00
        e01 += t01
        e03 += t03
        e10 += t10
        e11 += t11
        e13 += t13
        e20 += t20
        e21 += t21
        e23 += t23
    for _ in range(s):
        # e <- e e, with e[2, 2] = e[3, 3] = 1 and the other entries of column 2 and row 3 zero
        e00, e01, e03, e10, e11, e13, e20, e21, e23 = (
            e00 * e00 + e01 * e10, e00 * e01 + e01 * e11, e00 * e03 + e01 * e13 + e03,
            e10 * e00 + e11 * e10, e10 * e01 + e11 * e11, e10 * e03 + e11 * e13 + e13,
            e20 * e00 + e21 * e10 + e20, e20 * e01 + e21 * e11 + e21,
            e20 * e03 + e21 * e13 + e23 + e23)
    out[0] = e00
    out[1] = e01
    out[2] = e10
    out[3] = e11
    out[4] = e03
    out[5] = e13
    out[6] = e20
    out[7] = e21
    out[8] = e23
    out[9] = math.exp(-B * h)


@njit(cache=True)
def discretise_step(A, B, C, h, out):
    """Exact discretisation of one wheel over ``h`` seconds into ``out[:10]``.

    Same layout as :func:`mecanum_hil.model.motor.discretise` (without the trailing ``h``):
    ``a11 a12 a21 a22 b1 b2 cq1 cq2 dq exp(-B h)``. The closed form (~0.1 us) where it is well
    conditioned: it divides by ``C`` and subtracts terms of order ``(A + B) h`` to get terms of
    order ``C h^2``, which loses ``(A + B) h / (C h^2)`` (and ``(A + B) / A`` for the input
    terms) of the digits; elsewhere the Taylor series with scaling and squaring (~1 us).
    """
    apb = A + B
    ch2 = C * h * h
    if apb * h <= 40.0 and ch2 <= 400.0 and A > 0.0 and \
            ch2 >= 1e-4 * max(1.0, apb * h) * max(1.0, apb / A):
        _discretise_closed(A, B, C, h, out)
    else:
        _discretise_series(A, B, C, h, out)


@njit(cache=True)
def _discretise_kernel(coeffs, h_s, out):
    # serial: a few thousand rows take milliseconds, less than waking threads on a busy machine
    for r in range(coeffs.shape[0]):
        for j in range(h_s.size):
            discretise_step(coeffs[r, 0], coeffs[r, 1], coeffs[r, 2], h_s[j], out[r, j])
            out[r, j, 10] = h_s[j]


def discretise_many(coefficients, h_s) -> np.ndarray:
    """:func:`mecanum_hil.model.motor.discretise` for many coefficient sets, compiled.

    Parameters
    ----------
    coefficients : array_like, shape (M, 3)
        ``(A [1/s], B [1/s], C [1/s^2])`` rows.
    h_s : array_like, shape (K,)
        Step lengths [s].

    Returns
    -------
    ndarray, shape (M, K, 11)
        Table rows as :func:`~mecanum_hil.model.motor.discretise` gives them (equal to
        within about 1e-9 of each entry's natural scale: 1 for ``Ad``, ``C h`` for ``a12``,
        ``h`` for ``cq1``...); 0.1 to 1 microsecond per row instead of SciPy's ``expm`` per
        matrix.
    """
    co = np.ascontiguousarray(np.asarray(coefficients, dtype=float).reshape(-1, 3))
    h = np.ascontiguousarray(np.asarray(h_s, dtype=float).reshape(-1))
    out = np.empty((co.shape[0], h.size, TABLE_WIDTH))
    pick(_discretise_kernel, co.shape[0] * h.size)(co, h, out)
    return out
