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
    """One command as a ROS twist (REP-103: x forward, y left, z counter-clockwise).

    Parameters
    ----------
    n_rpm : float
        Wheel speed command [rpm].
    omega_dps : float
        Turning speed command [deg/s].
    theta_deg : float
        Direction of travel [deg].
    wheel_radius_m : float
        Wheel radius [m].

    Returns
    -------
    tuple of float
        ``(linear.x [m/s], linear.y [m/s], angular.z [rad/s])``.
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


def heard_command(sample, stamped: bool, wheel_radius_m: float, theta_deg: float
                  ) -> tuple[tuple[float, float, float], np.ndarray | None]:
    """A Twist (or TwistStamped) heard on a command topic, as ``import`` reads it.

    Returns
    -------
    twist : tuple of float
        ``(linear.x [m/s], linear.y [m/s], angular.z [rad/s])``.
    command : ndarray, shape (3,), or None
        ``(n [rpm], omega [deg/s], theta [deg])``, theta held at ``theta_deg`` without a
        translation; None for a twist that is not finite.
    """
    from ...importers.rosbag import twist_to_commands

    tw = sample.twist if stamped else sample
    v = (tw.linear.x, tw.linear.y, tw.angular.z)
    if not all(math.isfinite(x) for x in v):
        return v, None
    return v, twist_to_commands([v[0]], [v[1]], [v[2]], wheel_radius_m, theta_deg)[0]


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


class RobotClock:
    """Times a ROS 2 robot's messages on the robot's own clock (the stateful part of a link).

    A message's time is its header stamp; where that is unset, the DDS source timestamp (the
    publisher's clock when it wrote the sample); where that is unset too, the receive time.
    Equal times (two messages of one control cycle, a coarse clock) are pushed 1 us apart,
    so the times a session sees increase; a time that runs back is kept as it is (the robot's
    clock restarted). The least ``receive - robot time`` is the clock's offset from the host.
    """

    def __init__(self) -> None:
        self.origin_ns: int | None = None
        self.last_ns: int | None = None
        #: Least ``receive - robot time`` seen [ns] (None before the first message).
        self.offset_ns: int | None = None
        #: How the last message was timed: ``header stamps``, ``source timestamps`` or
        #: ``receive times``.
        self.source = ""

    def time_ns(self, stamp_ns: int, source_ns: int, receive_ns: int) -> int:
        """The robot-clock time of one message [ns]."""
        if stamp_ns > 0:
            t, self.source = stamp_ns, "header stamps"
        elif source_ns > 0:
            t, self.source = source_ns, "source timestamps"
        else:
            t, self.source = receive_ns, "receive times"
        d = receive_ns - t
        self.offset_ns = d if self.offset_ns is None else min(self.offset_ns, d)
        if self.last_ns is not None and t == self.last_ns:
            t += 1000
        self.last_ns = t
        if self.origin_ns is None:
            self.origin_ns = t
        return t

    def time_of(self, msg, receive_ns: int) -> int:
        """:meth:`time_ns` of a taken sample with a header (its stamp and its sample info)."""
        info = getattr(msg, "sample_info", None)
        return self.time_ns(stamp_to_ns(msg.header.stamp.sec, msg.header.stamp.nanosec),
                            info.source_timestamp if info is not None else 0, receive_ns)

    def controller_us(self, t_ns: int) -> int:
        """``t_ns`` as a controller's 32-bit microsecond clock since the first message."""
        return ((t_ns - (self.origin_ns or t_ns)) // 1000) % (1 << 32)

    def robot_now_ns(self, host_now_ns: int) -> int:
        """The robot's clock now [ns], from the host's (the host's own without an offset)."""
        return host_now_ns - (self.offset_ns or 0)
