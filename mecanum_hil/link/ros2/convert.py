"""Pure conversions between ROS 2 messages and mecanum-hil's quantities.

The command mapping is the exact inverse of ``import``'s Twist conversion
(:func:`mecanum_hil.importers.rosbag.twist_to_commands`): a command ``(n, omega, theta)``
becomes the body twist ``vx = v sin theta``, ``vy = -v cos theta`` with ``v = n f(theta)``
(wheel-rpm units, then metres per second by the wheel radius) and ``angular.z`` = omega in
rad/s. JointState velocities [rad/s] become wheel rpm times each wheel's sign.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ...model.kinematics import command_to_twist
from ...units import RPM_TO_RAD_S, rpm_to_mps

#: Nanoseconds in a second.
NS = 1_000_000_000


def command_to_twist_si(n_rpm: float, omega_dps: float, theta_deg: float,
                        wheel_radius_m: float) -> tuple[float, float, float]:
    """One command as a ROS twist ``(linear.x [m/s], linear.y [m/s], angular.z [rad/s])``.

    ``x`` is forward and ``y`` left (REP-103); ``angular.z`` is counter-clockwise.
    """
    vx, vy, _ = command_to_twist(n_rpm, omega_dps, theta_deg)
    return (float(rpm_to_mps(vx, wheel_radius_m)), float(rpm_to_mps(vy, wheel_radius_m)),
            math.radians(float(omega_dps)))


def joint_wheel_rpm(names: Sequence[str], velocities: Sequence[float],
                    joints: Sequence[str], signs: np.ndarray) -> np.ndarray:
    """Wheel speeds 1..4 [rpm] of one JointState (NaN for a wheel it does not carry).

    Parameters
    ----------
    names, velocities : sequence
        The message's ``name`` and ``velocity`` [rad/s] (a shorter velocity array leaves the
        joints past its end without a speed).
    joints : sequence of str
        Joint names of wheels 1 FL, 2 FR, 3 RL, 4 RR.
    signs : ndarray, shape (4,)
        +1 or -1 per wheel.
    """
    index = {name: i for i, name in enumerate(names)}
    out = np.full(4, np.nan)
    for w, joint in enumerate(joints):
        i = index.get(joint)
        if i is not None and i < len(velocities):
            out[w] = float(velocities[i]) / RPM_TO_RAD_S * signs[w]
    return out


def wheel_rpm_to_joint_velocity(wheel_rpm: np.ndarray, signs: np.ndarray) -> list[float]:
    """Wheel speeds [rpm] as JointState velocities [rad/s] (the inverse of
    :func:`joint_wheel_rpm`)."""
    return [float(w * RPM_TO_RAD_S * s) for w, s in zip(wheel_rpm, signs, strict=True)]


def stamp_to_ns(sec: int, nanosec: int) -> int:
    """A ``builtin_interfaces/Time`` [ns] (0 when unset)."""
    return int(sec) * NS + int(nanosec)


def ns_to_stamp(t_ns: int) -> tuple[int, int]:
    """Nanoseconds to ``(sec, nanosec)`` of a ``builtin_interfaces/Time``."""
    sec, nanosec = divmod(int(t_ns), NS)
    return sec, nanosec


def yaw_to_quaternion(phi_deg: float) -> tuple[float, float, float, float]:
    """A heading [deg] as the quaternion ``(x, y, z, w)`` of a rotation about z."""
    half = math.radians(phi_deg) / 2.0
    return 0.0, 0.0, math.sin(half), math.cos(half)
