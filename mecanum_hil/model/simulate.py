"""The model's simulator: commands in, wheel speeds and pose out, for one robot or thousands.

:func:`simulate_batch` is the vectorised core (compiled, robots in parallel);
:func:`simulate` is the single-robot convenience on top of it. Both are pure: arrays and frozen
dataclasses in, a :class:`Trajectory` out. The work remembered between calls (time plans, what
is known of arrays declared :func:`unchanging`) lives in :mod:`mecanum_hil.model.plan_cache`.

Exactness. Commands are piecewise constant between samples. On the closed-form path (none of
the effects below; ``deadband``, ``wheel_gain`` and ``slip`` keep it) each wheel is advanced
with the exact zero-order-hold discretisation of its transfer function, for any (also
irregular) sample times; ``dead_time`` is exact too, by splitting the steps at the delayed
command changes. The pose is advanced with the exact solution for the body twist averaged over
each step, ``(X, Y, phi)(t + h) = (X, Y, phi)(t) * exp(h * twist_mean)`` on SE(2): a straight
run or a pure turn is exact to rounding, and a combined motion is second order in the step.
The paper instead integrates Euler steps with the heading of the previous tick, which is first
order and drifts on long curved paths.

The sub-stepped path is taken by a robot whose effects are nonlinear
(:attr:`~mecanum_hil.model.calibration.Effects.nonlinear`): ``saturation``, ``windup``,
``rate_limit``, or any of the drive's own dynamics
(:attr:`~mecanum_hil.model.calibration.Effects.drive_dynamics`: ``controller_period``,
``drive_lag``, ``breakaway``, ``braking_limit``, ``fast_decay``, ``friction``,
``drive_deadband``). Each step is split into sub-steps of at most ``max_substep_s``
(default 1 ms), as :func:`~mecanum_hil.model.stepper.step_plan` does for a control period.
The set-point ramp and the drive's mode (linear or at its output limit) are decided at the
start of each sub-step, and within a sub-step each mode is solved exactly; with the drive's own
dynamics a sub-step is further cut at the controller's ticks.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..errors import ConfigError
from . import plan_cache
from .calibration import Calibration
from .kinematics import DEFAULT_POSE
from .plan_cache import Plan, array_facts, bytes_of, remember
from .plan_cache import unchanging as unchanging  # part of this module's API (a fit's)
from .robot import RobotProfile


@dataclass(frozen=True)
class Trajectory:
    """Result of a simulation, in the style of python-control's time responses.

    Attributes
    ----------
    time_s : ndarray, shape (T,)
        Sample times [s].
    commands : ndarray, shape (N, T, 3)
        ``(n [rpm], omega [deg/s], theta [deg])`` in force from each sample to the next.
    wheel_rpm : ndarray, shape (N, T, 4)
        Wheel speeds 1..4 at each sample [rpm].
    pose : ndarray, shape (N, T, 3)
        ``(X [m], Y [m], phi [deg])`` at each sample.
    final_state : ndarray, shape (N, 21)
        Wheel state at the last sample (``y1..y4`` [rpm], ``z1..z4`` [rpm s], drive set-points
        ``u1..u4`` [rpm], then the drive's held and lagged outputs and the time to the
        controller's next tick), to continue a simulation with ``initial_state``.
    """

    time_s: np.ndarray
    commands: np.ndarray
    wheel_rpm: np.ndarray
    pose: np.ndarray
    final_state: np.ndarray

    def robot(self, i: int) -> Trajectory:
        """The trajectory of robot ``i`` alone (N = 1)."""
        sl = slice(i, i + 1)
        return Trajectory(self.time_s, self.commands[sl], self.wheel_rpm[sl], self.pose[sl],
                          self.final_state[sl])


#: numpy's own float64 dtype object (:func:`_float_array`).
_FLOAT64 = np.dtype(float)


def _float_array(a) -> np.ndarray:
    """``np.asarray(a, dtype=float)``, and ``a`` itself for any native float64 array: numpy
    makes a new view of one whose dtype is an equal copy of its own (an unpickled array, such
    as a diagnosis helper's recordings), and what :func:`unchanging` remembers goes by
    identity."""
    if type(a) is np.ndarray and a.dtype == _FLOAT64:
        return a
    return np.asarray(a, dtype=float)


def _times(time_s) -> np.ndarray:
    t = _float_array(time_s)
    facts = array_facts(t)
    if facts is not None and "times" in facts:
        return t
    if t.ndim != 1 or t.size < 1:
        raise ConfigError("time_s must be a 1-D array with at least one sample")
    if not np.isfinite(t).all() or (np.diff(t) <= 0).any():
        raise ConfigError("time_s must be finite and strictly increasing")
    if facts is not None:
        facts["times"] = True
    return t


def uniform_time(duration_s: float, rate_hz: float) -> np.ndarray:
    """Sample times ``0, 1/rate, ..., duration`` [s] (duration rounded to whole samples)."""
    n = round(duration_s * rate_hz)
    return np.arange(n + 1) / float(rate_hz)


def steady_state(calibration: Calibration, wheel_rpm, target_rpm) -> np.ndarray:
    """The model's state (``STATE_WIDTH`` values) in steady state at given wheel speeds.

    A recording that starts in motion starts the model here: each wheel at its measured speed
    ``y``, its drive holding it (``B y``; through a fast-decay drive the output whose push
    balances friction and the pole at ``y``), the integral ``z`` such that the PI output equals
    that drive for the wheel's set-point ``u`` (the target through deadband and wheel gain):
    ``A (u - y) + C z = B y``.

    Parameters
    ----------
    calibration : Calibration
    wheel_rpm : array_like, shape (4,)
        Wheel speeds [rpm].
    target_rpm : array_like, shape (4,)
        Wheel targets of the first command (inverse kinematics) [rpm].
    """
    from ._kernels import STATE_WIDTH, holding_drive

    e = calibration.effects
    y = np.asarray(wheel_rpm, dtype=float)
    # a target below either deadband is 0 (a drive that is off ramps from 0 when it is on)
    u = np.where(np.abs(target_rpm) < max(e.deadband_rpm, e.drive_deadband_rpm), 0.0,
                 np.asarray(target_rpm, dtype=float)) * np.asarray(e.gains)
    A, B, C = calibration.coefficients
    # the kernel's Python source: four numbers need no compiled code (mecanum_hil._jit)
    hold = np.array([holding_drive.py_func(B, e.coast_decel_rpm_per_s, e.no_load_rpm, float(v),
                                           e.friction_rpm_per_s) for v in y])
    state = np.zeros(STATE_WIDTH)
    state[:4] = y
    state[4:8] = (hold - A * (u - y)) / C
    state[8:12] = u
    state[12:16] = hold
    state[16:20] = hold
    return state


def _delayed(cmd: np.ndarray, src: np.ndarray, initial_command: np.ndarray) -> np.ndarray:
    """Commands (N, T, 3) seen through a dead time on its grid (the ``src`` of a
    :class:`~mecanum_hil.model.plan_cache.Plan`): (N, G, 3), C-contiguous and writable;
    ``initial_command`` (N, 3) before the first (``src`` -1, which are the first grid points:
    ``src`` never decreases)."""
    out = np.ascontiguousarray(cmd[:, np.maximum(src, 0), :])
    before = int(np.searchsorted(src, 0))
    if before:
        out[:, :before, :] = initial_command[:, None, :]
    return out


def _delay_grid(t: np.ndarray, cmd: np.ndarray, delay_s: float, initial_command: np.ndarray):
    """Refine the time grid so a dead time ``delay_s`` > 0 [s] is exact; return grid, delayed
    commands (N, G, 3) and each grid point's sample (-1: none)."""
    plan = plan_cache.plan(t, delay_s, None)
    return plan.grid, _delayed(cmd, plan.src, initial_command), plan.record


def _step_tables(calibs: Sequence[Calibration], h_uniq: np.ndarray) -> np.ndarray:
    """Discretisation tables of each calibration for the step lengths ``h_uniq`` [s] (a
    plan's), shape (N, K, 11).

    The tables come from the compiled :func:`~mecanum_hil.model.discretise.discretise_many`
    (equal to :func:`~mecanum_hil.model.motor.discretise` to rounding): recordings timed by a
    real clock have thousands of distinct step lengths, and SciPy's ``expm`` costs ~20 us
    per matrix against ~1 us compiled.
    """
    from .discretise import discretise_many

    # each distinct coefficient set once (a Jacobian's perturbations share most)
    rows: dict[tuple[float, float, float], int] = {}
    which = np.array([rows.setdefault(tuple(c.coefficients), len(rows)) for c in calibs],
                     dtype=np.int64)
    table = discretise_many(np.array(list(rows), dtype=float), h_uniq)
    return np.ascontiguousarray(table[which])


def simulate_batch(
    commands,
    time_s,
    calibration: Calibration | Sequence[Calibration],
    robot: RobotProfile | None = None,
    *,
    initial_pose=DEFAULT_POSE,
    initial_state=None,
    initial_command=None,
    max_substep_s: float = 1e-3,
    out: Trajectory | None = None,
    wheels=None,
    pose: bool = True,
) -> Trajectory:
    """Simulate N robots, each with its own command stream and calibration.

    Parameters
    ----------
    commands : array_like, shape (N, T, 3) or (T, 3)
        ``(n [rpm], omega [deg/s], theta [deg])``; row t is in force from ``time_s[t]`` to
        ``time_s[t + 1]`` (the last row is not used). A (T, 3) array is shared by all robots.
    time_s : array_like, shape (T,)
        Strictly increasing sample times [s]; need not be uniform.
    calibration : Calibration or sequence of N Calibration
        Coefficients and effects, one for all robots or one per robot.
    robot : RobotProfile, optional
        Geometry (default: the paper's robot).
    initial_pose : array_like, shape (3,) or (N, 3)
        ``(X [m], Y [m], phi [deg])`` at ``time_s[0]``; default ``(0, 0, 90)``.
    initial_state : array_like, shape (N, 21) or (N, 12), optional
        Wheel state to continue from (``Trajectory.final_state``; see
        :data:`~mecanum_hil.model._kernels.STATE_WIDTH`); default at rest. A 12-column state
        (wheels only) leaves the drive's own dynamics at zero.
    initial_command : array_like, shape (3,) or (N, 3), optional
        Command in force before ``time_s[0]`` (seen through a dead time); default zero.
    max_substep_s : float
        Longest sub-step on the sub-stepped path (saturation, rate limit) [s].
    out : Trajectory, optional
        A trajectory of the same shape whose arrays are overwritten instead of allocating new
        ones (a training loop or benchmark that simulates again and again).
    wheels : array_like of bool, shape (4,), optional
        The wheels to simulate (default: all four); the others are NaN in ``wheel_rpm`` and
        stay in their initial state. The wheels are independent given the commands, so those
        simulated are the same as in a full simulation; a fit of the measured wheels alone
        needs no more. Needs ``pose=False`` unless all four are simulated.
    pose : bool
        Whether to compute the pose; without, ``pose`` is NaN (a fit of wheel speeds alone).

    Returns
    -------
    Trajectory
    """
    robot = robot or RobotProfile()
    if not max_substep_s > 0:
        raise ConfigError(f"max_substep_s must be > 0 seconds, got {max_substep_s!r}")
    active = _active_wheels(wheels, pose)
    t = _times(time_s)
    cmd, calibs, shared = _robots_and_commands(commands, t, calibration)
    n_rob = len(calibs)
    pose0, state0, cmd0 = _initial_values(n_rob, initial_pose, initial_state, initial_command)
    # one command before the start for all robots (given once, or none)
    cmd0_shared = initial_command is None or np.ndim(initial_command) == 1
    wheel_rpm, poses, final_state = _output_arrays(out, n_rob, t.size)
    outputs = (wheel_rpm, poses, final_state, np.empty((n_rob, 3)))
    batch = _Batch(t, cmd, calibs, robot, shared, cmd0, cmd0_shared, state0, pose0, active,
                   bool(pose), outputs, _all_in_place(outputs))
    # Robots are simulated in groups sharing a time grid: the same dead time (its grid is split at
    # the delayed command changes) and the same path (sub-stepped or closed-form), so a robot's
    # result never depends on which other robots share its batch.
    keys = [(c.effects.dead_time_s, c.effects.nonlinear) for c in calibs]
    for key in sorted(set(keys)):
        delay, nonlinear = key
        members = np.flatnonzero([k == key for k in keys])
        _simulate_group(batch, members, delay, max_substep_s if nonlinear else None)
    return Trajectory(t, np.asarray(cmd), wheel_rpm, poses, final_state)


class _Batch(NamedTuple):
    """What :func:`simulate_batch` checked and prepared for all its robots (N of them)."""

    t: np.ndarray                 # (T,) sample times [s]
    cmd: np.ndarray               # (N, T, 3) commands (a broadcast view when shared)
    calibs: list[Calibration]     # (N,) one per robot
    robot: RobotProfile           # the geometry
    shared: np.ndarray | None     # (T, 3) the one command stream of all robots, or None
    cmd0: np.ndarray              # (N, 3) command before the start
    cmd0_shared: bool             # one command before the start for all robots
    state0: np.ndarray            # (N, STATE_WIDTH) initial states
    pose0: np.ndarray             # (N, 3) initial poses
    active: np.ndarray            # (4,) bool: the wheels to simulate
    pose: bool                    # whether to compute the pose
    outputs: tuple                # wheels (N, T, 4), poses (N, T, 3), final states, final poses
    in_place: bool                # whether the kernel may write views of ``outputs``


def _all_in_place(outputs: tuple) -> bool:
    """Whether the kernel can write views of every output array: C-contiguous, writable
    float64."""
    return all(o.flags.c_contiguous and o.flags.writeable and o.dtype == np.float64
               for o in outputs)


def _group_rows(members: np.ndarray, n_rob: int, in_place: bool) -> slice | np.ndarray:
    """A group's rows among the ``n_rob`` robots: a slice where its ``members`` are
    consecutive (a Jacobian's perturbed dead time is one robot), whose views the kernel reads
    and writes in place, else the member indices."""
    if members.size == n_rob:
        return slice(None)
    if in_place and members[-1] - members[0] + 1 == members.size:
        return slice(members[0], members[-1] + 1)
    return members


def _simulate_group(batch: _Batch, members: np.ndarray, delay: float,
                    max_substep_s: float | None) -> None:
    """Simulate the robots ``members`` of ``batch``, which share the dead time ``delay`` [s]
    and the path (sub-stepped at ``max_substep_s`` [s], None: closed-form), into
    ``batch.outputs``."""
    t, calibs = batch.t, batch.calibs
    whole = members.size == len(calibs)
    rows = _group_rows(members, len(calibs), batch.in_place)
    group = calibs if whole else [calibs[i] for i in members]
    plan = plan_cache.plan(t, delay, max_substep_s)
    gcmd = _group_commands(t, batch.cmd, batch.cmd0, members, whole, batch.shared,
                           batch.cmd0_shared, delay, plan)
    args = _kernel_inputs(group, batch.robot, gcmd, _step_tables(group, plan.h_uniq),
                          plan.didx, plan.nsub, np.ascontiguousarray(batch.state0[rows]),
                          np.ascontiguousarray(batch.pose0[rows]))
    _run_group((*args, batch.active, batch.pose, plan.record), rows, len(group), t.size,
               plan.substeps, batch.outputs)


def _active_wheels(wheels, pose: bool) -> np.ndarray:
    """The kernel's ``active``: the wheels to simulate, (4,) bool, read-only (one type for the
    compiled kernel)."""
    if wheels is None:
        from .stepper import ALL_WHEELS

        return ALL_WHEELS
    given = np.asarray(wheels)
    if given.shape != (4,) or given.dtype != bool:
        raise ConfigError(f"wheels must be 4 booleans, got {wheels!r}")
    if pose and not given.all():
        raise ConfigError("the pose needs all four wheels simulated: pass pose=False")
    active = given.copy()
    active.flags.writeable = False
    return active


def _robots_and_commands(commands, t: np.ndarray, calibration):
    """Check the commands and calibrations and bring them to one per robot.

    Returns the (N, T, 3) commands (a broadcast view when one stream is shared), the N
    calibrations and the shared stream, shape (T, 3), when the commands were one (a fit's
    Jacobian), else None.
    """
    given = _float_array(commands)
    cmd = given[None] if given.ndim == 2 else given
    if cmd.ndim != 3 or cmd.shape[1:] != (t.size, 3):
        raise ConfigError(f"commands must have shape (N, {t.size}, 3), got {cmd.shape}")
    facts = array_facts(given)
    if facts is None or "finite" not in facts:
        if not np.isfinite(np.sum(cmd)):  # one pass; any NaN or inf makes the sum non-finite
            raise ConfigError("commands contain NaN or infinite values")
        if facts is not None:
            facts["finite"] = True
    calibs = [calibration] if isinstance(calibration, Calibration) else list(calibration)
    n_rob = max(cmd.shape[0], len(calibs))
    shared = given if given.ndim == 2 else given[0] if cmd.shape[0] == 1 else None
    if cmd.shape[0] == 1 and n_rob > 1:
        cmd = np.broadcast_to(cmd, (n_rob, t.size, 3))
    if len(calibs) == 1:
        calibs = calibs * n_rob
    if len(calibs) != n_rob or cmd.shape[0] != n_rob:
        raise ConfigError(f"{cmd.shape[0]} command streams but {len(calibs)} calibrations")
    for c in calibs:
        if math.isfinite(c.effects.output_limit_rpm) and c.B <= 0:
            raise ConfigError(f"{c.source}: a drive output limit (saturation, windup) needs "
                              "B > 0")
    return cmd, calibs, shared


def _initial_values(n_rob: int, initial_pose, initial_state, initial_command):
    """Per robot: initial pose (N, 3), state (N, ``STATE_WIDTH``) and command before the start
    (N, 3), each broadcast from what was given (a 12-column state is padded with zeros)."""
    from ._kernels import STATE_WIDTH, WHEEL_STATE_WIDTH

    pose0 = np.empty((n_rob, 3))
    pose0[:] = np.asarray(initial_pose, float)
    state0 = np.zeros((n_rob, STATE_WIDTH))
    if initial_state is not None:
        given = np.asarray(initial_state, float)
        if given.shape[-1] not in (WHEEL_STATE_WIDTH, STATE_WIDTH):
            raise ConfigError(f"initial_state must have {STATE_WIDTH} (or {WHEEL_STATE_WIDTH}) "
                              f"columns, got shape {given.shape}")
        state0[:, :given.shape[-1]] = given
    cmd0 = (np.zeros((n_rob, 3)) if initial_command is None
            else np.broadcast_to(np.asarray(initial_command, float), (n_rob, 3)))
    return pose0, state0, cmd0


#: Outputs larger than this [bytes] are touched from one thread before the kernel writes them
#: (a fit's small ones, thousands of times, need not be).
_TOUCH_BYTES = 1 << 20


def _output_arrays(out: Trajectory | None, n_rob: int, n_t: int):
    """Wheel speeds (N, T, 4), poses (N, T, 3) and final states to write: ``out``'s, or new."""
    from ._kernels import STATE_WIDTH

    if out is not None:
        if out.wheel_rpm.shape != (n_rob, n_t, 4) or out.pose.shape != (n_rob, n_t, 3):
            raise ConfigError("out= trajectory has the wrong shape for these commands")
        return out.wheel_rpm, out.pose, out.final_state
    wheels = np.empty((n_rob, n_t, 4))
    pose = np.empty((n_rob, n_t, 3))
    if wheels.nbytes + pose.nbytes > _TOUCH_BYTES:
        # Touch the output pages from one thread first: on these machines, first-touch page
        # faults taken from several threads at once were several times slower than doing so.
        # (The kernel writes every element: this is for speed only.)
        wheels.fill(0.0)
        pose.fill(0.0)
    return wheels, pose, np.empty((n_rob, STATE_WIDTH))


def _group_commands(t: np.ndarray, cmd: np.ndarray, cmd0: np.ndarray, members: np.ndarray,
                    whole: bool, shared: np.ndarray | None, cmd0_shared: bool, delay: float,
                    plan: Plan):
    """A group's commands on its grid (``plan``'s): with a dead time, as the wheels see them.
    ``shared``: the one command stream of all robots, (T, 3), or None; ``cmd0_shared``: one
    command before the start for all."""
    one = (shared is not None and members.size > 1
           and (cmd0_shared or bool(np.all(cmd0[members] == cmd0[members[0]]))))
    if one:  # the robots' (delayed) commands are one stream: computed once, not copied
        gcmd = np.broadcast_to(cmd[0], (members.size, t.size, 3))
    else:
        gcmd = cmd if whole else cmd[members]
    if not delay > 0:
        return gcmd
    if one or members.size == 1:
        # one stream (a fit's Jacobian, or its lone trial point) through the same dead time
        # again and again: its delayed commands are remembered
        first = remember(
            ("delayed", bytes_of(t), float(delay),
             bytes_of(shared) if shared is not None else gcmd[0].tobytes(),
             cmd0[members[0]].tobytes()),
            lambda: (_delayed(gcmd[:1], plan.src, cmd0[members[:1]]),))[0]
        if one:
            return np.broadcast_to(first[0], (members.size, first.shape[1], 3))
        return first.copy()  # writable, as a group's own are: one kernel type
    return _delayed(gcmd, plan.src, cmd0[members])


def _kernel_inputs(group: Sequence[Calibration], robot: RobotProfile, gcmd: np.ndarray,
                   table: np.ndarray, didx: np.ndarray, nsub: np.ndarray, state0: np.ndarray,
                   pose0: np.ndarray) -> tuple:
    """The arguments of :func:`~mecanum_hil.model._kernels.simulate_kernel` before its
    outputs."""
    from .stepper import effect_arrays

    return (
        gcmd, didx, nsub, table,  # any strides: a view is not copied
        np.array([c.coefficients for c in group], dtype=float),
        float(robot.k), float(robot.wheel_radius_m),
        *effect_arrays([c.effects for c in group]),
        state0, pose0,
    )


def _run_group(args: tuple, rows: slice | np.ndarray, n_rob: int, n_samples: int,
               substeps: int, outputs: tuple) -> None:
    """Run the kernel for a group and write its results into the rows ``rows`` of ``outputs``
    (wheels, pose, final state, final pose): in place where ``rows`` is a slice (the kernel
    writes the samples of its grid, ``record``), else through copies."""
    from .._jit import pick
    from ._kernels import STATE_WIDTH, simulate_kernel

    # a small job runs in the interpreter: numba's start-up costs more than it (_jit.py)
    kernel = pick(simulate_kernel, n_rob * max(substeps, 1))
    if isinstance(rows, slice):
        kernel(*args, *(o[rows] for o in outputs))
        return
    part = (np.empty((n_rob, n_samples, 4)), np.empty((n_rob, n_samples, 3)),
            np.empty((n_rob, STATE_WIDTH)), np.empty((n_rob, 3)))
    kernel(*args, *part)
    for full, mine in zip(outputs, part, strict=True):
        full[rows] = mine


def simulate(
    commands,
    time_s,
    calibration: Calibration | None = None,
    robot: RobotProfile | None = None,
    **kwargs,
) -> Trajectory:
    """Simulate one robot; ``commands`` has shape (T, 3). See :func:`simulate_batch`."""
    cmd = _float_array(commands)
    if cmd.ndim != 2:
        raise ConfigError(f"commands must have shape (T, 3), got {cmd.shape}")
    # one stream, (T, 3), as given: an array declared unchanging stays itself
    return simulate_batch(cmd, time_s, calibration or Calibration(), robot, **kwargs)
