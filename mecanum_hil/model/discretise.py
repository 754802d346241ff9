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
def _expm4(m):
    # scaling and squaring with a Taylor series: ||m / 2^s|| <= 1/4, 18 terms leave a
    # truncation error far below rounding, for the 4 x 4 augmented wheel model
    norm = 0.0
    for i in range(4):
        row = 0.0
        for j in range(4):
            row += abs(m[i, j])
        norm = max(norm, row)
    s = 0
    while norm > 0.25:
        norm *= 0.5
        s += 1
    a = m / (2.0 ** s)
    out = np.eye(4)
    term = np.eye(4)
    for n in range(1, 19):
        term = term @ a / n
        out += term
    for _ in range(s):
        out = out @ out
    return out


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
    m = np.zeros((4, 4))
    m[0, 0] = -(A + B) * h
    m[0, 1] = C * h
    m[0, 3] = A * h
    m[1, 0] = -h
    m[1, 3] = h
    m[2, 0] = h
    e = _expm4(m)
    out[0] = e[0, 0]
    out[1] = e[0, 1]
    out[2] = e[1, 0]
    out[3] = e[1, 1]
    out[4] = e[0, 3]
    out[5] = e[1, 3]
    out[6] = e[2, 0]
    out[7] = e[2, 1]
    out[8] = e[2, 3]
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
