"""Recordings made ready for a fit: :func:`prepare` checks them and keeps, per recording, what
the least squares of :mod:`mecanum_hil.identify.fit` needs (:class:`Prepared`: commands, times,
measured channels and their masks, the start in motion); :func:`pose_scale` weighs pose
residuals against wheel speeds.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import FitError
from ..io.recording import Recording
from ..model.calibration import Calibration
from ..model.kinematics import command_to_wheels
from ..model.robot import RobotProfile
from ..model.simulate import steady_state, unchanging
from ..prediction import (
    controller_clock_s,
    initial_wheel_rpm,
    require_commands,
    start_pose,
    with_tick_phase,
    without_frozen_start,
)
from ..units import RPM_TO_RAD_S


@dataclass(frozen=True)
class Prepared:
    """One recording ready for the model: commands, times, measured channels and masks."""

    t_s: np.ndarray
    commands: np.ndarray
    wheel_rpm: np.ndarray         # (T, 4) measured, NaN where not
    wheel_mask: np.ndarray        # (T, 4) bool
    pose: np.ndarray              # (T, 3) measured, NaN where not
    pose_mask: np.ndarray         # (T, 3) bool
    pose0: tuple[float, float, float]
    pose_scale: np.ndarray        # (3,) pose residual -> wheel-rpm equivalent
    source: str
    start_rpm: np.ndarray         # (4,) wheel speeds at the start (0: at rest)
    start_target: np.ndarray      # (4,) wheel targets of the first command [rpm]
    clock_s: float | None = None  # the controller's clock at the first sample [s]

    @functools.cached_property
    def wheel_measured(self) -> np.ndarray:
        """The wheels measured somewhere in the recording, (4,) bool."""
        return self.wheel_mask.any(axis=0)

    @functools.cached_property
    def wheel_index(self) -> np.ndarray:
        """Flat indices of the measured wheel samples in a (T, 4) array (C order)."""
        return np.flatnonzero(self.wheel_mask.ravel())

    @functools.cached_property
    def wheel_values(self) -> np.ndarray:
        """The measured wheel speeds [rpm], in the order of :attr:`wheel_index`."""
        return self.wheel_rpm.ravel()[self.wheel_index]

    def wheel_residuals(self, wheels: np.ndarray) -> np.ndarray:
        """Measured minus model wheel speeds at the measured samples, one row per model:
        ``wheels`` (M, T, 4) [rpm] -> (M, measured samples)."""
        flat = wheels.reshape(wheels.shape[0], -1)
        # laid out as a boolean mask's result (Fortran order): sums over it then run in the
        # same order, and a fit follows the same path to the last bit
        return (self.wheel_values[:, None] - flat.T[self.wheel_index]).T

    def initial_states(self, calibs: Sequence[Calibration]) -> np.ndarray | None:
        """Steady states at the measured start speeds, with the controller's tick phase, one per
        calibration; None for the default (at rest, first tick at the first sample)."""
        phased = self.clock_s is not None and any(
            c.effects.controller_period_s > 0 for c in calibs)
        if not self.start_rpm.any() and not phased:
            return None
        return np.stack([with_tick_phase(steady_state(c, self.start_rpm, self.start_target),
                                         c, self.clock_s) for c in calibs])


def pose_scale(duration_s: float, robot: RobotProfile) -> np.ndarray:
    """Factors turning pose residuals ``(x [m], y [m], phi [deg])`` into wheel-rpm equivalents
    [rpm/m, rpm/m, rpm/deg], for a recording of ``duration_s`` [s].

    A position error ``e`` [m] accumulated over the recording's duration ``T`` is what a constant
    wheel-speed error of ``e / (T r 2 pi / 60)`` [rpm] would cause; a heading error ``e`` [deg]
    likewise corresponds to a turning-speed error ``e / T`` [deg/s], which the kinematics turns
    into ``k e / (6 T)`` [rpm] at the wheels.
    """
    T = max(float(duration_s), 1e-9)
    pos = 1.0 / (T * RPM_TO_RAD_S * robot.wheel_radius_m)
    return np.array([pos, pos, robot.k / (6.0 * T)])


def source_name(i: int, rec: Recording, sources: Sequence[str] | None) -> str:
    """The name of recording ``i`` for the provenance: ``sources[i]`` where given, else the
    file it was read from, else ``recording <i + 1>``."""
    if sources is not None and i < len(sources):
        return str(sources[i])
    return str(rec.metadata.get("source_file", f"recording {i + 1}"))


def prepare(recordings: Sequence[Recording], robot: RobotProfile,
            sources: Sequence[str] | None = None) -> list[Prepared]:
    """Check recordings and keep what a fit needs.

    Parameters
    ----------
    recordings : sequence of Recording
        Commands and measured wheel speeds (and poses) of each run.
    robot : RobotProfile
        Geometry for the kinematics.
    sources : sequence of str, optional
        Names of the recordings for the provenance (:func:`source_name`).

    Returns
    -------
    list of Prepared
        One per recording, in their order.

    Raises
    ------
    FitError
        Without recordings, without any measured wheel speed, or without excitation (every wheel
        target zero: the model at rest explains nothing).
    RecordingError
        For a recording whose command columns are not all filled.
    """
    if not recordings:
        raise FitError("no recordings given")
    out: list[Prepared] = []
    for i, rec in enumerate(recordings):
        src = source_name(i, rec, sources)
        require_commands(rec, src)
        start = initial_wheel_rpm(rec)
        rec = without_frozen_start(rec)
        wheel = np.asarray(rec.wheel_rpm, dtype=float)
        pose = np.asarray(rec.pose, dtype=float)
        pose0 = start_pose(rec)
        out.append(Prepared(
            _unchanging(rec.t_s), _unchanging(rec.commands), wheel,
            np.isfinite(wheel), pose, np.isfinite(pose), pose0,
            pose_scale(rec.t_s[-1] - rec.t_s[0], robot), src, start,
            command_to_wheels(rec.commands[:1, 0], rec.commands[:1, 1], rec.commands[:1, 2],
                              robot.k)[0], controller_clock_s(rec)))
    n = sum(int(p.wheel_mask.sum()) for p in out)
    if n == 0:
        raise FitError("no measured wheel speed in the recordings (wheel1_rpm..wheel4_rpm are "
                       "all empty); fit needs wheel speeds from telemetry or video")
    targets = [command_to_wheels(p.commands[:, 0], p.commands[:, 1], p.commands[:, 2], robot.k)
               for p in out]
    if all(np.all(np.abs(w[:-1]) < 1e-12) for w in targets):
        raise FitError("no excitation: every wheel target is zero (the robot was never commanded "
                       "to move), so the data cannot identify the model")
    measured = np.concatenate([p.wheel_rpm[p.wheel_mask] for p in out])
    if np.ptp(measured) == 0.0:
        raise FitError("no excitation: every measured wheel speed has the same value")
    return out


def _unchanging(a) -> np.ndarray:
    """A private copy of ``a`` (float) that nothing changes: the simulator remembers what it
    learnt about it (its bytes, its checks) instead of redoing it on every simulation. (Not
    made read-only: numba compiles its kernels again for read-only arguments.)"""
    return unchanging(np.array(a, dtype=float))
