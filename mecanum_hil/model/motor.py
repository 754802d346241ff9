"""The wheel model's state space and its exact discretisation (pure, vectorised).

State of one wheel: ``y`` wheel speed [rpm] and ``z`` integral of the speed error [rpm s]::

    drive = A (u - y) + C z        (PI output, as an acceleration [rpm/s])
    dy/dt = drive - B y
    dz/dt = u - y

whose transfer function from target ``u`` to ``y`` is ``(A s + C) / (s^2 + (A + B) s + C)``.

For a target held constant over a step of ``h`` seconds the update is exact (zero-order hold,
through the matrix exponential of the system augmented with the input and with ``q``, the
integral of ``y`` over the step, which the pose integration needs)::

    [y, z](t + h) = Ad [y, z](t) + Bd u
    q = integral of y over the step = Cq [y, z](t) + Dq u
"""

from __future__ import annotations

import numpy as np

#: Number of values in one row of a discretisation table (see :func:`discretise`).
TABLE_WIDTH = 11


def discretise(A, B, C, h_s):
    """Exact zero-order-hold discretisation, broadcast over its arguments.

    Parameters
    ----------
    A, B, C : float or array_like
        Wheel model coefficients [1/s], [1/s], [1/s^2].
    h_s : float or array_like
        Step length [s].

    Returns
    -------
    ndarray, shape (..., 11)
        Rows ``(a11, a12, a21, a22, b1, b2, cq1, cq2, dq, exp(-B h), h)``: ``Ad``, ``Bd``,
        ``Cq``, ``Dq`` as in the module docstring, the decay factor used by the saturated drive,
        and the step length itself.
    """
    A, B, C, h = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (A, B, C, h_s)))
    shape = A.shape
    A, B, C, h = (v.reshape(-1) for v in (A, B, C, h))
    m = np.zeros((A.size, 4, 4))
    # augmented state (y, z, q, u): u constant, q' = y
    m[:, 0, 0] = -(A + B)
    m[:, 0, 1] = C
    m[:, 0, 3] = A
    m[:, 1, 0] = -1.0
    m[:, 1, 3] = 1.0
    m[:, 2, 0] = 1.0
    from scipy.linalg import expm  # here, not at import: scipy.linalg costs ~0.1 s to load

    e = expm(m * h[:, None, None])
    out = np.empty((A.size, TABLE_WIDTH))
    out[:, 0] = e[:, 0, 0]
    out[:, 1] = e[:, 0, 1]
    out[:, 2] = e[:, 1, 0]
    out[:, 3] = e[:, 1, 1]
    out[:, 4] = e[:, 0, 3]
    out[:, 5] = e[:, 1, 3]
    out[:, 6] = e[:, 2, 0]
    out[:, 7] = e[:, 2, 1]
    out[:, 8] = e[:, 2, 3]
    out[:, 9] = np.exp(-B * h)
    out[:, 10] = h
    return out.reshape(*shape, TABLE_WIDTH)


def transfer_function(A: float, B: float, C: float):
    """Numerator and denominator of ``(A s + C) / (s^2 + (A + B) s + C)`` (scipy.signal order)."""
    return np.array([A, C], dtype=float), np.array([1.0, A + B, C], dtype=float)


def poles(A: float, B: float, C: float) -> np.ndarray:
    """Poles of the wheel model [1/s]."""
    return np.roots([1.0, A + B, C])
