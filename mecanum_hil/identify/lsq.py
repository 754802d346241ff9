"""Bounded Levenberg-Marquardt for small smooth fits, and Student's t quantile, without SciPy.

Importing :mod:`scipy.optimize` costs about 0.3 s of CPU on the project's 2-core machine (it
pulls in scipy.linalg, scipy.sparse and scipy.fft), and :mod:`scipy.special` another 0.05-0.1 s:
more than a whole fit of the paper's three coefficients on a short recording takes. ``fit`` uses
:func:`levenberg_marquardt` for exactly that problem (the paper's model, no effect, a few
parameters, a smooth cost) and SciPy's trust-region reflective method for everything else
(effects make the cost non-smooth where a limit switches on, and ``diagnose`` relies on its
behaviour there). ``diagnose``'s generic reference model (a linear output-error model, a
smooth cost) is refined with it too: SciPy's ``lm`` gave results that depended on what the
process had done before (identify/diagnose/reference.py). Both stop at the same minimum of a
smooth cost to within their tolerances (tests/identify/test_lsq.py).

The method: Moré's Levenberg-Marquardt with the damping scaled by the Jacobian's column norms
(SciPy's ``x_scale="jac"``), steps projected onto the bounds, a gain ratio that decides whether a
step is taken and how the damping changes (Nielsen's rule), and SciPy's stopping tests
(``ftol``, ``xtol``, ``gtol``, ``max_nfev``) with SciPy's status codes, so that a caller can
treat the result as it treats :func:`scipy.optimize.least_squares`' own.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

_MESSAGES = {
    -1: "no step lowered the cost: the residuals are not finite around the point reached",
    0: "the maximum number of function evaluations is exceeded",
    1: "gtol termination condition is satisfied",
    2: "ftol termination condition is satisfied",
    3: "xtol termination condition is satisfied",
    4: "both ftol and xtol termination conditions are satisfied",
    5: "stalled: the cost fell by less than the stall tolerance over the last evaluations",
}


@dataclass(frozen=True)
class Solution:
    """What :func:`levenberg_marquardt` found (the fields a caller of SciPy's reads).

    Attributes
    ----------
    x : ndarray
        The parameters.
    cost : float
        Half the sum of squared residuals at ``x``.
    status : int
        SciPy's codes: 0 evaluations exhausted, 1 gtol, 2 ftol, 3 xtol, 4 ftol and xtol; -1
        every step refused because the residuals there are not finite (a failure); and 5, a
        search stopped by its caller because it stalled (``mecanum_hil.identify.search``).
    nfev : int
        Residual evaluations.
    message : str
        ``status`` in words.
    """

    x: np.ndarray
    cost: float
    status: int
    nfev: int
    message: str


def levenberg_marquardt(fun: Callable[[np.ndarray], np.ndarray],
                        jac: Callable[[np.ndarray], np.ndarray], x0, lower, upper, *,
                        max_nfev: int, ftol: float = 1e-8, xtol: float = 1e-8,
                        gtol: float = 1e-8) -> Solution:
    """Minimise ``0.5 ||fun(x)||^2`` for ``lower <= x <= upper``.

    Parameters
    ----------
    fun, jac : callable
        Residuals, shape (m,), and their Jacobian, shape (m, n), at ``x``.
    x0 : array_like, shape (n,)
        Start (clipped into the bounds).
    lower, upper : array_like, shape (n,)
        Bounds (``-inf`` / ``inf`` where there is none).
    max_nfev : int
        Most evaluations of ``fun``.
    ftol, xtol, gtol : float
        SciPy's stopping tolerances: relative decrease of the cost, relative step, and the
        scaled gradient's largest component.

    Returns
    -------
    Solution

    Raises
    ------
    ValueError
        When the residuals at the start are not finite.
    """
    lo = np.asarray(lower, dtype=float)
    hi = np.asarray(upper, dtype=float)
    x, r, cost, J, scale = _first_point(fun, jac, x0, lo, hi)
    nfev = 1
    mu = None
    nu = 2.0
    while True:
        g = J.T @ r
        # a component pushing against the bound it sits on is no reason to go on
        free = ~(((x <= lo) & (g > 0)) | ((x >= hi) & (g < 0)))
        if np.max(np.abs(g * free) / scale, initial=0.0) < gtol * max(1.0, 2.0 * cost) ** 0.5:
            return solution(x, cost, 1, nfev)
        if nfev >= max_nfev:
            return solution(x, cost, 0, nfev)
        JtJ = J.T @ J
        if mu is None:
            mu = 1e-3 * float(np.max(np.diag(JtJ) / scale ** 2))
        step = _damped_step(JtJ, g, free, mu, scale, x)
        x_new = np.clip(x + step, lo, hi)
        step = x_new - x
        r_new = np.asarray(fun(x_new), dtype=float)
        nfev += 1
        cost_new = 0.5 * float(r_new @ r_new) if np.all(np.isfinite(r_new)) else math.inf
        actual, rho = _gain(g, step, JtJ, cost, cost_new)
        small_step = np.linalg.norm(step * scale) < xtol * (xtol + np.linalg.norm(x * scale))
        if rho > 1e-4:
            small_cost = actual < ftol * cost
            x, r, cost = x_new, r_new, cost_new
            J = np.asarray(jac(x), dtype=float)
            scale = np.maximum(scale, np.linalg.norm(J, axis=0))
            mu *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            nu = 2.0
            if small_cost or small_step:
                return solution(x, cost, _accepted_status(small_cost, small_step), nfev)
        else:
            if small_step and np.isfinite(cost_new):
                return solution(x, cost, 3, nfev)
            mu *= nu
            nu *= 2.0
            if not math.isfinite(mu) or mu > 1e300:
                # no step, however short, lowers the cost: where the residuals are finite
                # around x that is a minimum (the step test); where every trial point failed
                # (non-finite residuals) it is not, and the search failed
                return solution(x, cost, 3 if np.isfinite(cost_new) else -1, nfev)


def _first_point(fun: Callable[[np.ndarray], np.ndarray],
                 jac: Callable[[np.ndarray], np.ndarray], x0, lo: np.ndarray, hi: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, np.ndarray]:
    """The start ``x0`` clipped into the bounds: the point, its residuals and cost, its
    Jacobian and the Jacobian's column norms (1 for a zero column).

    Raises
    ------
    ValueError
        When the residuals at the start are not finite.
    """
    x = np.clip(np.asarray(x0, dtype=float), lo, hi)
    r = np.asarray(fun(x), dtype=float)
    if not np.all(np.isfinite(r)):
        raise ValueError("residuals are not finite at the starting point")
    cost = 0.5 * float(r @ r)
    J = np.asarray(jac(x), dtype=float)
    scale = np.linalg.norm(J, axis=0)
    scale[scale == 0.0] = 1.0
    return x, r, cost, J, scale


def _damped_step(JtJ: np.ndarray, g: np.ndarray, free: np.ndarray, mu: float,
                 scale: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The damped Gauss-Newton step in the free components, zero in the others.

    A component held on its bound does not move, and the others are solved for without it
    (projecting a full step stalls on an active bound); where the damped normal equations are
    singular, a gradient step.

    Parameters
    ----------
    JtJ : ndarray, shape (n, n)
        ``J^T J`` at ``x``.
    g : ndarray, shape (n,)
        The gradient ``J^T r`` at ``x``.
    free : ndarray of bool, shape (n,)
        The components that may move.
    mu : float
        The damping, relative to ``scale**2``.
    scale : ndarray, shape (n,)
        The columns' norms (the largest seen).
    x : ndarray, shape (n,)
        The point, in the parameters' units.
    """
    step = np.zeros_like(x)
    sub = np.ix_(free, free)
    try:
        step[free] = np.linalg.solve(JtJ[sub] + mu * np.diag(scale[free] ** 2), -g[free])
    except np.linalg.LinAlgError:
        step[free] = -g[free] / (mu * scale[free] ** 2)
    return step


def _gain(g: np.ndarray, step: np.ndarray, JtJ: np.ndarray, cost: float,
          cost_new: float) -> tuple[float, float]:
    """The actual decrease of the cost over ``step``, and its ratio to the decrease the
    quadratic model predicted (-1 where it predicted none)."""
    predicted = -(g @ step + 0.5 * step @ JtJ @ step)
    actual = cost - cost_new
    return actual, (actual / predicted if predicted > 0 else -1.0)


def _accepted_status(small_cost: bool, small_step: bool) -> int:
    """The status of a search ended on an accepted step: 4 both tests, 2 ``ftol``, 3 ``xtol``."""
    return 4 if small_cost and small_step else 2 if small_cost else 3


def solution(x: np.ndarray, cost: float, status: int, nfev: int) -> Solution:
    """A :class:`Solution` with ``status``'s message (``x`` copied)."""
    return Solution(np.array(x, dtype=float), float(cost), status, nfev, _MESSAGES[status])


@functools.lru_cache(maxsize=1024)
def t_quantile(p: float, dof: float) -> float:
    """Student's t quantile: the ``t`` with ``P(T <= t) = p`` for ``dof`` degrees of freedom.

    Newton's method on the distribution function through the regularised incomplete beta
    function (continued fraction). Against :func:`scipy.special.stdtrit`: relative error below
    1e-10 for 1 <= ``dof`` <= 1e6 and 1e-15 < ``p`` < 1 - 1e-15 (tested), 1e-8 up to
    ``dof`` = 1e9; meant for interval quantiles (``fit``: p = 0.975, dof = residuals - parameters).
    Remembered per ``(p, dof)``: ``diagnose`` asks for the same few hundreds of times (the
    continued fraction converges slowly for large ``dof``: about 1 s of a 5-s diagnosis).

    Parameters
    ----------
    p : float
        Probability, in (0, 1).
    dof : float
        Degrees of freedom, > 0.
    """
    if not (0.0 < p < 1.0 and 0.5 <= dof < 1e12):
        raise ValueError(f"need 0 < p < 1 and 0.5 <= dof < 1e12, got p={p!r}, dof={dof!r}")
    if p == 0.5:
        return 0.0
    if p < 0.5:
        return -t_quantile(1.0 - p, dof)
    tail = 1.0 - p
    # start from the normal quantile with the Cornish-Fisher correction, then Newton on the
    # upper tail (where the precision is), in log space for large t
    z = _normal_quantile(p)
    t = z + (z ** 3 + z) / (4.0 * dof) + (5 * z ** 5 + 16 * z ** 3 + 3 * z) / (96.0 * dof ** 2)
    t = max(t, 1e-8)
    log_norm = _lgamma_half_ratio(dof / 2) - 0.5 * math.log(dof * math.pi)
    for _ in range(100):
        upper = _t_upper(t, dof)
        pdf = math.exp(log_norm - (dof + 1) / 2 * math.log1p(t * t / dof))
        step = (upper - tail) / pdf
        if step < -t / 2:   # too large a step towards 0 on a heavy tail: halve instead
            step = -t / 2
        t += step
        if abs(step) <= 1e-15 * max(abs(t), 1.0):
            break
    return t


def _t_upper(t: float, dof: float) -> float:
    """P(T > t) for t >= 0."""
    # x and its complement each computed directly: near 1 a difference would lose the digits
    return 0.5 * _betainc(dof / 2.0, 0.5, dof / (dof + t * t), t * t / (dof + t * t))


def _lgamma_half_ratio(a: float) -> float:
    """``lgamma(a + 1/2) - lgamma(a)``; for large ``a`` by its asymptotic series (the two
    lgammas are large and nearly equal there: their difference would keep few digits)."""
    if a < 50.0:
        return math.lgamma(a + 0.5) - math.lgamma(a)
    u = 1.0 / a
    return 0.5 * math.log(a) - u / 8.0 + u ** 3 / 192.0 - u ** 5 / 640.0 + 17.0 * u ** 7 / 14336.0


def _betainc(a: float, b: float, x: float, y: float) -> float:
    """Regularised incomplete beta function I_x(a, b) with ``y = 1 - x`` given exactly, for
    ``b = 1/2`` or ``a = 1/2`` (Student's t); continued fraction (Lentz)."""
    if x <= 0.0:
        return 0.0
    if y <= 0.0:
        return 1.0
    if x > (a + 1.0) / (a + b + 2.0):
        return 1.0 - _betainc(b, a, y, x)
    big = a if b == 0.5 else b
    # the log of a number near 1 from its small complement: a large a or b multiplies its error
    log_x = math.log1p(-y) if y < 0.5 else math.log(x)
    log_y = math.log1p(-x) if x < 0.5 else math.log(y)
    log_front = _lgamma_half_ratio(big) - math.lgamma(0.5) + a * log_x + b * log_y
    return math.exp(log_front) * _betacf(a, b, x) / a


def _betacf(a: float, b: float, x: float) -> float:
    tiny = 1e-300
    qab, qap, qam = a + b, a + 1.0, a - 1.0
    c, d = 1.0, 1.0 - qab * x / qap
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, 10_000):
        m2 = 2 * m
        aa = m * (b - m) * x / ((qam + m2) * (a + m2))
        d = 1.0 + aa * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + aa / c
        c = c if abs(c) > tiny else tiny
        h *= d * c
        aa = -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2))
        d = 1.0 + aa * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + aa / c
        c = c if abs(c) > tiny else tiny
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < 1e-16:
            break
    return h


def _normal_quantile(p: float) -> float:
    """Standard normal quantile (Acklam's rational approximation, ~1e-9; a start value only)."""
    a = (-3.969683028665376e+01, 2.209460984245205e+02, -2.759285104469687e+02,
         1.383577518672690e+02, -3.066479806614716e+01, 2.506628277459239e+00)
    b = (-5.447609879822406e+01, 1.615858368580409e+02, -1.556989798598866e+02,
         6.680131188771972e+01, -1.328068155288572e+01)
    c = (-7.784894002430293e-03, -3.223964580411365e-01, -2.400758277161838e+00,
         -2.549732539343734e+00, 4.374664141464968e+00, 2.938163982698783e+00)
    d = (7.784695709041462e-03, 3.224671290700398e-01, 2.445134137142996e+00,
         3.754408661907416e+00)
    q = min(p, 1.0 - p)
    if q < 0.02425:
        s = math.sqrt(-2.0 * math.log(q))
        z = (((((c[0] * s + c[1]) * s + c[2]) * s + c[3]) * s + c[4]) * s + c[5]) / \
            ((((d[0] * s + d[1]) * s + d[2]) * s + d[3]) * s + 1.0)
    else:
        s = q - 0.5
        r = s * s
        z = (((((a[0] * r + a[1]) * r + a[2]) * r + a[3]) * r + a[4]) * r + a[5]) * s / \
            (((((b[0] * r + b[1]) * r + b[2]) * r + b[3]) * r + b[4]) * r + 1.0)
    return z if p < 0.5 else -z  # z is the quantile of min(p, 1 - p)
