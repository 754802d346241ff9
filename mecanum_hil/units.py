"""Unit conversions, in one place.

The model works in the paper's units: wheel speeds and body velocities in wheel revolutions per
minute [rpm], turning speed in degrees per second [deg/s], angles in degrees, positions in metres.
A body velocity "in wheel-rpm units" is the wheel speed that would produce it with no slip.
"""

from __future__ import annotations

import math

#: One wheel revolution per minute expressed in radians per second.
RPM_TO_RAD_S = 2.0 * math.pi / 60.0

#: A body turning speed of 1 deg/s expressed in body revolutions per minute (60 / 360).
DPS_TO_RPM = 1.0 / 6.0


def rpm_to_mps(speed_rpm, wheel_radius_m: float):
    """Wheel-rpm units to metres per second.

    Parameters
    ----------
    speed_rpm : float or ndarray
        Speed in wheel revolutions per minute [rpm].
    wheel_radius_m : float
        Wheel radius [m].

    Returns
    -------
    float or ndarray
        Rim speed [m/s].
    """
    return speed_rpm * RPM_TO_RAD_S * wheel_radius_m


def mps_to_rpm(speed_mps, wheel_radius_m: float):
    """Metres per second to wheel-rpm units (inverse of :func:`rpm_to_mps`)."""
    return speed_mps / (RPM_TO_RAD_S * wheel_radius_m)


#: A turning speed of 1 rpm (one revolution per minute) in degrees per second.
DPS_PER_RPM = 6.0

#: Time units of logged time columns, in seconds.
TIME_UNITS_S = {"s": 1.0, "ms": 1e-3, "us": 1e-6}

#: Wheel-speed units of logged speed columns (``counts/s`` also needs counts per revolution).
SPEED_UNITS = ("rpm", "rad/s", "deg/s", "counts/s")


def speed_to_rpm(values, unit: str, counts_per_rev: float | None = None):
    """A wheel speed in one of :data:`SPEED_UNITS` to revolutions per minute [rpm].

    Parameters
    ----------
    values : float or ndarray
        Speeds in ``unit``.
    unit : str
        ``rpm``, ``rad/s``, ``deg/s`` (of wheel rotation) or ``counts/s`` (encoder counts).
    counts_per_rev : float, optional
        Encoder counts per wheel revolution [-], required for ``counts/s``.
    """
    if unit == "rpm":
        return values * 1.0
    if unit == "rad/s":
        return values / RPM_TO_RAD_S
    if unit == "deg/s":
        return values / DPS_PER_RPM
    if unit == "counts/s":
        if not counts_per_rev:
            raise ValueError("counts/s needs counts_per_rev")
        return values * (60.0 / counts_per_rev)
    raise ValueError(f"unknown speed unit {unit!r} (known: {', '.join(SPEED_UNITS)})")
