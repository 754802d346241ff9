"""The model's prediction for a recording's commands, as a recording (pure)."""

from __future__ import annotations

from typing import Any

import numpy as np

from . import __version__
from .errors import RecordingError
from .io.recording import Recording
from .model.calibration import Calibration
from .model.robot import RobotProfile
from .model.simulate import DEFAULT_POSE, Trajectory, simulate


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


def predict(rec: Recording, calibration: Calibration, robot: RobotProfile,
            initial_pose=None, source: str = "recording") -> Recording:
    """Simulate the model on a recording's commands and times.

    The initial pose is :func:`start_pose` unless given. Extra columns are kept.
    """
    require_commands(rec, source)
    if initial_pose is None:
        initial_pose = start_pose(rec)
    traj = simulate(rec.commands, rec.t_s, calibration, robot, initial_pose=initial_pose)
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
