"""How a fit searches: the solver for a problem, stopping a search that stalls, restarts.

:func:`solver` picks the least-squares method for a problem (Levenberg-Marquardt of
:mod:`mecanum_hil.identify.lsq` for the paper's smooth model, SciPy's trust-region reflective
method otherwise), :func:`stall_stopped` ends a search whose cost has stopped falling
(:func:`check_stall`) at its best point, and :func:`restarted` goes on from where a search
stopped on its step test.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import numpy as np

from ..errors import FitError
from ..model.calibration import Calibration
from .parameters import COEFFICIENTS, NO_EFFECTS

#: Restarts of a least-squares search that stopped on its step test, and the least relative
#: decrease of the cost for which one more is tried.
MAX_RESTARTS = 8
RESTART_GAIN = 1e-4
#: A search whose best cost fell by less than ``RESTART_GAIN`` (relative) over its last
#: ``max(STALL_MIN_EVALUATIONS, STALL_EVALUATIONS_PER_PARAMETER x free parameters)``
#: evaluations is stopped at its best point (status 5, not restarted): in a corner of the model
#: (C -> 0) a trust-region search can creep along a valley, each step lowering the cost by more
#: than ``ftol`` and all of them together by less than 1e-4, until its evaluations run out
#: (800 evaluations, 23 s of a 59-s campaign diagnosis, for 6e-5 of the cost).
STALL_EVALUATIONS_PER_PARAMETER = 15
STALL_MIN_EVALUATIONS = 40


class SearchStalledError(Exception):
    """A watched search stalled (:data:`STALL_EVALUATIONS_PER_PARAMETER`); carries its best
    point as a :class:`~mecanum_hil.identify.lsq.Solution` with status 5."""

    def __init__(self, solution) -> None:
        super().__init__(solution.message)
        self.solution = solution


def check_stall(trace: Sequence[float], best: tuple[float, np.ndarray] | None,
                free_count: int) -> None:
    """Raise :class:`SearchStalledError` where a watched search stalled.

    Parameters
    ----------
    trace : sequence of float
        The search's best cost [rpm^2 / 2] after each of its evaluations.
    best : (float, ndarray) or None
        Its best cost and the point where it was reached.
    free_count : int
        The number of free parameters.

    Raises
    ------
    SearchStalledError
        When the best cost fell by less than :data:`RESTART_GAIN` (relative) over the last
        ``max(STALL_MIN_EVALUATIONS, STALL_EVALUATIONS_PER_PARAMETER x free_count)``
        evaluations, with the best point.
    """
    window = max(STALL_MIN_EVALUATIONS, STALL_EVALUATIONS_PER_PARAMETER * free_count)
    if len(trace) > window:
        before = trace[-1 - window]
        if math.isfinite(before) and trace[-1] > (1.0 - RESTART_GAIN) * before:
            from .lsq import solution

            cost, x_best = best
            raise SearchStalledError(solution(x_best, cost, 5, len(trace)))


def smooth(calibration: Calibration, live: Sequence[str], pose: bool) -> bool:
    """Whether a problem is the paper's model alone (no effect, only A, B, C free, wheel speeds
    only): a smooth cost."""
    return calibration.effects == NO_EFFECTS and set(live) <= set(COEFFICIENTS) and not pose


def solver(calibration: Calibration, live: Sequence[str], pose: bool):
    """The least-squares method for a problem: ``solve(problem, x0, lower, upper, max_nfev)``.

    The paper's model (no effect, only A, B, C free, wheel speeds only) has a smooth cost:
    :func:`mecanum_hil.identify.lsq.levenberg_marquardt`, which needs no SciPy (its import
    costs more than such a fit). Everything else: SciPy's trust-region reflective method,
    whose handling of the kinks an effect's limit puts in the cost ``diagnose`` relies on.
    """
    if smooth(calibration, live, pose):
        from .lsq import levenberg_marquardt

        @stall_stopped
        def solve(problem, x0, lo, hi, max_nfev):
            size = problem.fun(x0).size

            def fun(x):
                # a step projected onto the bounds can land on A = B = 0 (no stable model):
                # an infinite cost, so the step is refused and the damping grows
                try:
                    return problem.fun(x)
                except FitError:
                    return np.full(size, np.inf)
            return levenberg_marquardt(fun, problem.jac, x0, lo, hi, max_nfev=max_nfev)
        return solve

    @stall_stopped
    def solve(problem, x0, lo, hi, max_nfev):
        from scipy.optimize import least_squares

        # a trial step far out (a candidate's corner) overflows in the trust region's own
        # arithmetic, which refuses that step and shrinks the region: scipy's warning about
        # it is not the user's (it printed six lines on a diagnose of a campaign)
        with np.errstate(over="ignore", invalid="ignore"):
            return least_squares(problem.fun, x0, jac=problem.jac, bounds=(lo, hi),
                                 x_scale="jac", method="trf", max_nfev=max_nfev)
    return solve


def stall_stopped(solve):
    """``solve`` that watches its problem and ends a stalled search at its best point."""
    @functools.wraps(solve)
    def run(problem, x0, lo, hi, max_nfev):
        problem.watch(x0)
        try:
            return solve(problem, x0, lo, hi, max_nfev)
        except SearchStalledError as stop:
            return stop.solution
        finally:
            problem.unwatch()
    return run


def restarted(problem, sol, lo, hi, max_nfev: int, solve):
    """``sol`` improved by fresh searches from where it stopped on its step test.

    Where a drive limit switches on, the cost is not smooth: the finite-difference Jacobian
    misleads the trust region, which shrinks until the step test (``xtol``, ``ftol``: status
    2, 3, 4) ends the search well before the minimum. A fresh trust region from there goes on;
    restart while that lowers the cost by ``RESTART_GAIN``. A restart that runs out of
    evaluations still counts when it is lower (it stops the restarts); one that fails is
    dropped, keeping the converged result.
    """
    for _ in range(MAX_RESTARTS):
        if sol.status not in (2, 3, 4):
            break
        try:
            again = solve(problem, sol.x, lo, hi, max_nfev)
        except (ValueError, np.linalg.LinAlgError):
            break
        if not (np.isfinite(again.cost) and again.cost < (1.0 - RESTART_GAIN) * sol.cost):
            break
        sol = again
    return sol
