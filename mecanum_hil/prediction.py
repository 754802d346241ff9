"""The model's prediction for a recording's commands, as a recording (pure)."""

from __future__ import annotations

from typing import Any

import numpy as np

from . import __version__
from .errors import RecordingError
from .io.recording import Recording
from .model.calibration import Calibration
from .model.kinematics import command_to_wheels
from .model.robot import RobotProfile
from .model.simulate import DEFAULT_POSE, Trajectory, simulate, steady_state

#: A wheel reading repeated unchanged for at least this many samples at the start of a
#: recording is a frozen sensor value (a stale reading), not motion.
FROZEN_SAMPLES = 5
#: Samples averaged for the initial speed of a recording that starts in motion.
START_SAMPLES = 3
#: A start below this speed [rpm] (or four noise levels) is taken as rest.
REST_RPM = 2.0


def require_commands(rec: Recording, source: str = "recording") -> None:
    """Refuse a recording whose command columns are not all filled."""
    if len(rec) < 2:
        raise RecordingError(f"{source}: needs at least two samples, has {len(rec)}")
    missing = ~np.isfinite(rec.commands).all(axis=1)
    if missing.any():
        i = int(np.argmax(missing))
        raise RecordingError(
            f"{source}: the command columns are empty at t_s={rec.t_s[i]:g} (row {i + 1}); "
            "the model needs n_cmd_rpm, omega_cmd_dps and theta_cmd_deg on every row")


def trajectory_to_recording(traj: Trajectory, metadata: dict[str, Any] | None = None,
                            extra=None) -> Recording:
    """Robot 0 of a trajectory as a recording (wheel and pose columns filled)."""
    return Recording(traj.time_s.copy(), traj.commands[0].copy(), traj.wheel_rpm[0].copy(),
                     traj.pose[0].copy(), dict(extra or {}), dict(metadata or {}))


def first_moving_row(rec: Recording) -> int:
    """Index of the first row whose command moves the robot (``n`` or ``omega`` not zero);
    ``len(rec)`` when none does."""
    c = np.asarray(rec.commands, dtype=float)
    moving = (np.abs(c[:, 0]) > 1e-9) | (np.abs(c[:, 1]) > 1e-9)  # NaN: not moving
    return int(np.argmax(moving)) if moving.any() else len(rec)


def start_pose(rec: Recording) -> tuple[float, float, float]:
    """Where the model starts a recording.

    Parameters
    ----------
    rec : Recording

    Returns
    -------
    (float, float, float)
        The first measured pose ``(X [m], Y [m], phi [deg])`` if it was measured before the
        robot moves (a recording's first rows may be commands without a pose), else
        ``(0 m, 0 m, 90 deg)``.
    """
    pose = np.asarray(rec.pose, dtype=float)
    rows = np.flatnonzero(np.isfinite(pose).all(axis=1))
    # the row at which the first moving command is sent is still at rest
    if rows.size and rows[0] <= first_moving_row(rec):
        return tuple(float(v) for v in pose[rows[0]])
    return tuple(DEFAULT_POSE)


def frozen_start(rec: Recording) -> np.ndarray:
    """Mask (T, 4) of the leading samples whose reading is frozen: a non-zero value repeated
    unchanged for at least :data:`FROZEN_SAMPLES` samples from the first measured one."""
    w = np.asarray(rec.wheel_rpm, dtype=float)
    out = np.zeros(w.shape, bool)
    for i in range(4):
        rows = np.flatnonzero(np.isfinite(w[:, i]))
        if rows.size < FROZEN_SAMPLES:
            continue
        v = w[rows, i]
        run = int(np.argmax(v != v[0])) if (v != v[0]).any() else v.size
        if run >= FROZEN_SAMPLES and v[0] != 0.0:
            out[rows[:run], i] = True
    return out


def without_frozen_start(rec: Recording) -> Recording:
    """The recording with frozen leading readings (:func:`frozen_start`) emptied."""
    mask = frozen_start(rec)
    if not mask.any():
        return rec
    w = np.array(rec.wheel_rpm, dtype=float)
    w[mask] = np.nan
    return rec.with_values(wheel_rpm=w)


def _reading_at_start(rec: Recording, rows: np.ndarray) -> bool:
    """Whether a wheel's first reading (``rows``: its measured rows) may tell its speed at the
    recording's start: it is on the first row; or the rows before it carry no reading of any
    wheel (a recorded run's command rows), under the same command, within one of the wheel's
    sampling periods (:func:`initial_wheel_rpm` then also asks that it is not accelerating)."""
    first = int(rows[0])
    if first == 0:
        return True
    if rows.size < 2 or np.isfinite(rec.wheel_rpm[:first]).any():
        return False
    period = float(np.median(np.diff(rec.t_s[rows[:20]])))
    cmd = rec.commands[:first + 1]
    same = bool(np.all((cmd == cmd[0]) | (np.isnan(cmd) & np.isnan(cmd[0]))))
    return same and rec.t_s[first] - rec.t_s[0] <= period


def initial_wheel_rpm(rec: Recording) -> np.ndarray:
    """Wheel speeds [rpm] the model starts from: 0 at rest, else the first measured reading,
    averaged with those of the next :data:`START_SAMPLES` - 1 that agree with it within four
    noise levels (a wheel already accelerating is not averaged away). A first reading below
    :data:`REST_RPM` or four noise levels (from the first differences) is rest; a frozen reading
    is not motion (that wheel starts at rest); a wheel without a reading at the start starts at
    rest. The start is the first sample, or the first reading when only rows without any (a
    recorded run's command rows) come before it, with the same command, within one of the
    wheel's sampling periods, and the wheel is not accelerating there."""
    w = np.asarray(without_frozen_start(rec).wheel_rpm, dtype=float)
    out = np.zeros(4)
    frozen = frozen_start(rec).any(axis=0)
    for i in range(4):
        rows = np.flatnonzero(np.isfinite(w[:, i]))
        if frozen[i] or rows.size == 0 or not _reading_at_start(rec, rows):
            continue
        d = np.diff(w[rows[:20], i])
        sigma = float(1.4826 * np.median(np.abs(d)) / np.sqrt(2.0)) if d.size > 2 else 0.0
        first = w[rows[0], i]
        if abs(first) <= max(REST_RPM, 4.0 * sigma):
            continue
        if rows[0] > 0 and abs(w[rows[1], i] - first) > max(4.0 * sigma, REST_RPM):
            continue  # after command rows, a wheel accelerating: a step at the first row
        near = w[rows[:START_SAMPLES], i]
        near = near[np.abs(near - first) <= max(4.0 * sigma, REST_RPM)]
        out[i] = float(near.mean())
    return out


def controller_clock_s(rec: Recording) -> float | None:
    """The controller's clock at the first sample [s], from a ``controller_time_s`` column
    (the controller's time of each telemetry row); ``None`` without one. A controller that
    computes its output every ``T`` seconds ticks at whole multiples of ``T`` on this clock."""
    if "controller_time_s" not in rec.extra:
        return None
    c = rec.extra_numeric("controller_time_s")
    rows = np.flatnonzero(np.isfinite(c))
    if rows.size == 0:
        return None
    j = int(rows[0])
    return float(c[j] - (rec.t_s[j] - rec.t_s[0]))


def initial_state(rec: Recording, calibration: Calibration, robot: RobotProfile,
                  clock_s: float | None = None):
    """The model's state at the first sample, or ``None`` for the default (at rest, the
    controller's first tick at the first sample).

    A recording that starts in motion starts in steady state at the measured speeds
    (:func:`~mecanum_hil.model.simulate.steady_state`); with a ``controller_period`` and the
    controller's clock known (:func:`controller_clock_s`, or ``clock_s``), the first tick is
    placed where that clock reaches a whole period.
    """
    y0 = initial_wheel_rpm(rec)
    clock = controller_clock_s(rec) if clock_s is None else clock_s
    period = calibration.effects.controller_period_s
    phased = period > 0 and clock is not None
    if not y0.any() and not phased:
        return None
    c = np.asarray(rec.commands[0], dtype=float)
    tg = command_to_wheels(c[None, 0], c[None, 1], c[None, 2], robot.k)[0]
    return with_tick_phase(steady_state(calibration, y0, tg), calibration, clock)


def with_tick_phase(state: np.ndarray, calibration: Calibration, clock_s: float | None):
    """``state`` with the time to the controller's next tick set from its clock at the first
    sample (unchanged without a controller period or a clock)."""
    period = calibration.effects.controller_period_s
    if period > 0 and clock_s is not None:
        state = np.array(state, dtype=float)
        state[..., 20] = (-clock_s) % period
        if state[..., 20] >= period - 1e-12:
            state[..., 20] = 0.0
    return state


def model_start(rec: Recording, calibration: Calibration, robot: RobotProfile) -> dict:
    """How the model starts a recording, as keyword arguments of
    :func:`~mecanum_hil.model.simulate.simulate`: in steady state at the measured speeds and
    with the first command already acting when it starts in motion (:func:`initial_state`);
    at rest otherwise."""
    moving = initial_wheel_rpm(rec).any()
    return {"initial_state": initial_state(rec, calibration, robot),
            "initial_command": rec.commands[0] if moving else None}


def predict(rec: Recording, calibration: Calibration, robot: RobotProfile,
            initial_pose=None, source: str = "recording") -> Recording:
    """Simulate the model on a recording's commands and times.

    The initial pose is :func:`start_pose` unless given; a recording that starts in motion
    starts the model in steady state at the measured speeds (:func:`initial_state`). Extra
    columns are kept.
    """
    require_commands(rec, source)
    if initial_pose is None:
        initial_pose = start_pose(rec)
    traj = simulate(rec.commands, rec.t_s, calibration, robot, initial_pose=initial_pose,
                    **model_start(rec, calibration, robot))
    meta = {
        "source": "mecanum-hil simulate",
        "commands_from": source,
        "robot_profile": robot.source,
        "calibration": calibration.source,
        "coefficients": {"A": calibration.A, "B": calibration.B, "C": calibration.C},
        "effects": calibration.effects.active(),
        "tool_version": __version__,
        "sample_rate_hz": float(1.0 / np.median(np.diff(rec.t_s))),
        "notes": "the model's prediction for the commands of " + source,
    }
    return trajectory_to_recording(traj, meta, rec.extra)
