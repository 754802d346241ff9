"""A low-level array API to the simulator: N robots advanced one control period at a time.

:func:`~mecanum_hil.model.simulate_batch` takes whole command streams and lists of
:class:`Calibration` objects; called once per control period for thousands of robots its
per-call Python work (validation, discretising, grouping by dead time) would dominate. This
module keeps everything the compiled kernel needs as arrays, built once:

* the coefficients ``(A, B, C)`` per robot as an ``(N, 3)`` array, with the discretisation
  tables for the fixed control period cached per coefficient set (:func:`step_tables`) and
  computed in compiled code when new sets arrive (domain randomisation draws thousands);
* the effects' parameters as arrays (:func:`effect_arrays`, shared with ``simulate_batch``);
* a command delay line, because ``simulate_batch`` is exact across a dead time only within one
  call: here each period is split at the instant the delayed command changes, as
  ``simulate_batch`` splits its grid, so stepping period by period reproduces one long call.

:class:`BatchStepper` is the small stateful shell (wheel state, pose, delay line) around the
pure kernel ``mecanum_hil.model._kernels.simulate_kernel``, always compiled (a stepper steps
thousands of times); creating one imports numba.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from .calibration import Calibration, Effects, check_model_coefficients
from .discretise import discretise_many, discretise_step  # noqa: F401 (re-exported)
from .kinematics import DEFAULT_POSE
from .motor import TABLE_WIDTH
from .robot import RobotProfile

#: The kernel's ``active`` for all four wheels (a stepper's, and ``simulate_batch``'s default):
#: read-only, as the simulator's other plans, so the compiled kernel sees one type.
ALL_WHEELS = np.ones(4, dtype=bool)
ALL_WHEELS.flags.writeable = False

#: Default longest sub-step on the sub-stepped path (saturation, rate limit) [s].
DEFAULT_MAX_SUBSTEP_S = 1e-3

# Largest number of coefficient sets kept in the table cache before it is cleared.
_CACHE_LIMIT = 16384
_TABLE_CACHE: dict[tuple, np.ndarray] = {}


def effect_arrays(effects: Sequence[Effects]) -> tuple[np.ndarray, ...]:
    """The effects' parameters as the kernel's per-robot arrays.

    Parameters
    ----------
    effects : sequence of N Effects

    Returns
    -------
    tuple of ndarray
        ``deadband (N,)`` [rpm], ``gains (N, 4)`` [-], ``top_speed (N,)`` [rpm] (the output
        limit of ``saturation`` or ``windup``), ``rate_limit (N,)`` [rpm/s], ``efficiency (N,
        3)`` [-], ``drive (N, 9)`` (controller period [s], drive lag [s], breakaway [rpm/s],
        braking limit [rpm/s], the fast-decay drive's coasting deceleration [rpm/s] and
        no-load speed [rpm], 1 where the output limit has no anti-windup, else 0, Coulomb
        friction [rpm/s], drive deadband [rpm]), in the kernel's argument order.
    """
    return (
        np.array([e.deadband_rpm for e in effects], dtype=float),
        np.array([e.gains for e in effects], dtype=float),
        np.array([e.output_limit_rpm for e in effects], dtype=float),
        np.array([e.rate_limit_rpm_per_s for e in effects], dtype=float),
        np.array([e.efficiency for e in effects], dtype=float),
        np.array([(e.controller_period_s, e.drive_lag_s, e.breakaway_rpm_per_s,
                   e.braking_limit_rpm_per_s, e.coast_decel_rpm_per_s, e.no_load_rpm,
                   float(e.windup), e.friction_rpm_per_s, e.drive_deadband_rpm)
                  for e in effects], dtype=float).reshape(-1, 9),
    )


def substeps(dt_s: np.ndarray, max_substep_s: float | None) -> np.ndarray:
    """Number of sub-steps for steps of ``dt_s`` [s] (1 each on the closed-form path)."""
    if max_substep_s is None:
        return np.ones(dt_s.size, dtype=np.int64)
    return np.maximum(1, np.ceil(dt_s / max_substep_s - 1e-9)).astype(np.int64)


@dataclass(frozen=True)
class StepPlan:
    """How one control period is cut into pieces for the kernel.

    Attributes
    ----------
    period_s : float
        Control period [s].
    delay_periods : int
        Whole control periods inside the dead time.
    piece_s : ndarray, shape (P,)
        Lengths of the P pieces of one period [s] (P = 2 when the dead time is not a whole
        number of periods: the delayed command changes inside the period).
    nsub : ndarray, shape (P,)
        Sub-steps per piece.
    """

    period_s: float
    delay_periods: int
    piece_s: np.ndarray
    nsub: np.ndarray

    @property
    def substep_s(self) -> np.ndarray:
        """Sub-step length of each piece [s]; the rows of a discretisation table."""
        return self.piece_s / self.nsub


def step_plan(period_s: float, effects: Effects,
              max_substep_s: float = DEFAULT_MAX_SUBSTEP_S) -> StepPlan:
    """Cut one control period at the dead time's command change, as ``simulate_batch`` does.

    A command sent at ``t_j`` acts from ``t_j + dead_time_s = t_(j + m) + r`` with ``m`` whole
    periods and a remainder ``r``: within the period after ``t_k`` the command of ``t_(k-m-1)``
    acts for ``r`` seconds, then that of ``t_(k-m)``.
    """
    h = float(period_s)
    if not (math.isfinite(h) and h > 0):
        raise ConfigError(f"control period must be a positive number of seconds, got {h!r}")
    d = float(effects.dead_time_s)
    m = math.floor(d / h + 1e-9)
    r = d - m * h
    # simulate_batch merges breakpoints closer than 1e-9 s; so does this
    pieces = np.array([h]) if r <= 1e-9 or h - r <= 1e-9 else np.array([r, h - r])
    if h - r <= 1e-9 and r > 1e-9:
        m += 1
    nsub = substeps(pieces, max_substep_s if effects.nonlinear else None)
    return StepPlan(h, m, pieces, nsub)


def step_tables(coefficients, substep_s) -> np.ndarray:
    """Discretisation tables for N robots, cached per coefficient set and sub-step lengths.

    Parameters
    ----------
    coefficients : array_like, shape (N, 3)
        ``(A, B, C)`` per robot.
    substep_s : array_like, shape (P,)
        Sub-step lengths of the pieces of one control period [s] (:attr:`StepPlan.substep_s`).

    Returns
    -------
    ndarray, shape (N, P, 11)
    """
    co = np.asarray(coefficients, dtype=float).reshape(-1, 3)
    hs = tuple(float(v) for v in np.asarray(substep_s, dtype=float).reshape(-1))
    distinct, which = np.unique(co, axis=0, return_inverse=True)
    keys = [(*map(float, row), hs) for row in distinct]
    missing = [i for i, key in enumerate(keys) if key not in _TABLE_CACHE]
    if missing:
        if len(_TABLE_CACHE) + len(missing) > _CACHE_LIMIT:
            _TABLE_CACHE.clear()  # then every set of this call is missing
            missing = list(range(len(keys)))
        fresh = discretise_many(distinct[missing], np.array(hs))
        for i, rows in zip(missing, fresh, strict=True):
            _TABLE_CACHE[keys[i]] = rows
    tables = np.stack([_TABLE_CACHE[key] for key in keys])
    return np.ascontiguousarray(tables[which.reshape(-1)])


class BatchStepper:
    """N robots of one calibration's effects, advanced one control period per :meth:`step`.

    The coefficients may differ per robot (domain randomisation); the effects and the control
    period are shared. State lives in plain arrays that callers may read (and, between steps,
    write): ``state`` (N, 12) as ``Trajectory.final_state``, ``pose`` (N, 3) ``(X [m], Y [m],
    phi [deg])`` with phi not wrapped, as :func:`~mecanum_hil.model.simulate` returns it.

    Parameters
    ----------
    n_robots : int
        Number of robots N.
    period_s : float
        Control period [s]: a command given to :meth:`step` is held for this long.
    calibration : Calibration
        Coefficients (for all robots until :meth:`set_coefficients`) and effects.
    robot : RobotProfile, optional
        Geometry (default: the paper's robot).
    max_substep_s : float
        Longest sub-step on the sub-stepped path (saturation, rate limit) [s].
    num_threads : int, optional
        Threads the kernel may use per step (default 1; ``None``: numba's default). One step
        of even 4096 robots is a millisecond of work, and on a loaded machine the threads'
        meeting at the end of every parallel step cost more than the work (measured: 4096
        robots 8.6 ms with 2 threads against 2.2 ms with 1 while other jobs ran).
    """

    def __init__(self, n_robots: int, period_s: float, calibration: Calibration,
                 robot: RobotProfile | None = None, *,
                 max_substep_s: float = DEFAULT_MAX_SUBSTEP_S,
                 num_threads: int | None = 1) -> None:
        import numba

        from .._jit import compiled
        from ._kernels import STATE_WIDTH, simulate_kernel

        self._kernel = compiled(simulate_kernel)  # stepped thousands of times: always compiled
        self._numba = numba
        self.num_threads = (numba.config.NUMBA_NUM_THREADS if num_threads is None
                            else max(1, min(int(num_threads), numba.config.NUMBA_NUM_THREADS)))
        n = int(n_robots)
        if n < 1:
            raise ConfigError(f"n_robots must be at least 1, got {n_robots!r}")
        self.n_robots = n
        self.robot = robot or RobotProfile()
        self.effects = calibration.effects
        self.plan = step_plan(period_s, self.effects, max_substep_s)
        pieces = self.plan.piece_s.size
        self._effect_args = tuple(
            np.ascontiguousarray(np.broadcast_to(a, (n, *a.shape[1:])))
            for a in effect_arrays([self.effects]))
        self._saturating = math.isfinite(self.effects.output_limit_rpm)
        self.coefficients = np.empty((n, 3))
        self._tables = np.empty((n, pieces, TABLE_WIDTH))
        self.set_coefficients(np.array(calibration.coefficients))
        self.state = np.zeros((n, STATE_WIDTH))
        self.pose = np.zeros((n, 3))
        # delay line: slot (step mod L) holds the command sent at that step
        self._history = np.zeros((n, self.plan.delay_periods + 2, 3))
        self._step = 0
        self._cmd = np.zeros((n, pieces + 1, 3))
        self._didx = np.append(np.arange(pieces, dtype=np.int64), 0)
        self._nsub = np.append(self.plan.nsub, 0).astype(np.int64)
        self._record = np.arange(pieces + 1, dtype=np.int64)
        for plan in (self._didx, self._nsub, self._record):
            plan.flags.writeable = False  # as the simulator's (memoised): one kernel type
        self._wheels_out = np.zeros((n, pieces + 1, 4))
        self._pose_out = np.zeros((n, pieces + 1, 3))

    @property
    def wheel_rpm(self) -> np.ndarray:
        """Wheel speeds 1..4 [rpm], shape (N, 4) (a view of ``state``)."""
        return self.state[:, :4]

    def set_coefficients(self, coefficients, index=None) -> None:
        """Set ``(A, B, C)`` for all robots or for those in ``index``.

        Parameters
        ----------
        coefficients : array_like, shape (3,) or (M, 3)
        index : array_like of int or bool mask, optional
            Robots to change (default: all).
        """
        idx = slice(None) if index is None else index
        rows = np.broadcast_to(np.asarray(coefficients, dtype=float),
                               self.coefficients[idx].shape)
        if rows.size == 0:
            return
        for A, B, C in np.unique(rows.reshape(-1, 3), axis=0):
            check_model_coefficients(A, B, C, "coefficients")
            if self._saturating and B <= 0:
                raise ConfigError("coefficients: a drive output limit (saturation, windup) "
                                  "needs B > 0")
        self.coefficients[idx] = rows
        self._tables[idx] = step_tables(rows, self.plan.substep_s).reshape(
            self._tables[idx].shape)

    def reset(self, index=None, pose=DEFAULT_POSE, state=None, command=None) -> None:
        """Put robots (all, or those in ``index``) at a pose, at rest or in a given state.

        Parameters
        ----------
        index : array_like of int or bool mask, optional
        pose : array_like, shape (3,) or (M, 3)
            ``(X [m], Y [m], phi [deg])``.
        state : array_like, shape (12,) or (M, 12), optional
            Wheel state (default at rest).
        command : array_like, shape (3,) or (M, 3), optional
            Command taken as in force before now, seen through the dead time (default zero).
        """
        idx = slice(None) if index is None else index
        self.pose[idx] = pose
        self.state[idx] = 0.0 if state is None else state
        c = np.zeros(3) if command is None else np.asarray(command, dtype=float)
        self._history[idx] = c[..., None, :] if c.ndim == 2 else c

    def step(self, commands) -> None:
        """Hold ``commands`` (N, 3) ``(n [rpm], omega [deg/s], theta [deg])`` for one period.

        Updates ``state``, ``pose`` (and so ``wheel_rpm``) in place. Commands are used as given:
        limits are the caller's business (see ``RobotProfile.check_commands``).
        """
        hist = self._history
        size = hist.shape[1]
        hist[:, self._step % size] = commands
        m = self.plan.delay_periods
        pieces = self.plan.piece_s.size
        if pieces == 1:
            self._cmd[:, 0] = hist[:, (self._step - m) % size]
        else:
            self._cmd[:, 0] = hist[:, (self._step - m - 1) % size]
            self._cmd[:, 1] = hist[:, (self._step - m) % size]
        self._step += 1
        k = self.robot
        numba = self._numba
        previous = numba.get_num_threads()
        numba.set_num_threads(self.num_threads)
        try:
            # state and pose are read per robot before they are written: in-place is safe
            self._kernel(
                self._cmd, self._didx, self._nsub, self._tables, self.coefficients,
                float(k.k), float(k.wheel_radius_m), *self._effect_args,
                self.state, self.pose, ALL_WHEELS, True, self._record, self._wheels_out,
                self._pose_out, self.state, self.pose)
        finally:
            numba.set_num_threads(previous)
