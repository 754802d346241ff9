"""Mecanum kinematics of the paper's robot, vectorised (pure functions on arrays).

Conventions (pinned; see docs/conventions.md):

* Robot frame: x forward, y left (REP-103). Wheels 1 front-left, 2 front-right, 3 rear-left,
  4 rear-right; a positive wheel speed rolls the robot forward; rollers in X configuration.
* Commands: ``n`` [rpm], ``omega`` [deg/s] counter-clockwise positive, ``theta`` [deg] direction of
  travel counter-clockwise from the robot's right side (0 right, 90 ahead, 180 left, 270 back).
* Translation speed ``v = n f(theta)``, ``f(theta) = 1 / (|sin theta| + |cos theta|)``, so the
  fastest wheel of a pure translation turns at ``n``. Body velocity in wheel-rpm units:
  ``vx = v sin theta``, ``vy = -v cos theta``; turning speed in the same units ``wz = omega / 6``.
* With ``k = (lx + ly) / r``::

      w1 = vx - vy - k wz      w2 = vx + vy + k wz
      w3 = vx + vy - k wz      w4 = vx - vy + k wz

  and the forward kinematics is its pseudo-inverse.
"""

from __future__ import annotations

import numpy as np

from ..units import DPS_TO_RPM

#: The pose a simulation starts from unless told otherwise: the origin, facing world +Y
#: (x [m], y [m], phi [deg]; docs/conventions.md).
DEFAULT_POSE = (0.0, 0.0, 90.0)

#: Inverse kinematics matrix for k = 1: wheels = IK @ (vx, vy, k wz).
_IK = np.array(
    [[1.0, -1.0, -1.0], [1.0, 1.0, 1.0], [1.0, 1.0, -1.0], [1.0, -1.0, 1.0]]
)


def direction_scale(theta_deg):
    """The paper's direction scaling ``f(theta) = 1 / (|sin theta| + |cos theta|)`` [-].

    Parameters
    ----------
    theta_deg : float or array_like
        Direction of travel in the robot frame [deg].

    Returns
    -------
    ndarray
        Scale factor, between 1/sqrt(2) and 1.
    """
    th = np.deg2rad(np.asarray(theta_deg, dtype=float))
    return 1.0 / (np.abs(np.sin(th)) + np.abs(np.cos(th)))


def command_to_twist(n_rpm, omega_dps, theta_deg):
    """Commands to body twist in wheel-rpm units.

    Parameters
    ----------
    n_rpm : array_like
        Wheel speed command [rpm].
    omega_dps : array_like
        Turning speed command, counter-clockwise positive [deg/s].
    theta_deg : array_like
        Direction of travel in the robot frame [deg].

    Returns
    -------
    ndarray, shape (..., 3)
        ``(vx, vy, wz)`` [rpm]; ``wz`` is the body's turning speed in revolutions per minute.
    """
    n = np.asarray(n_rpm, dtype=float)
    th = np.deg2rad(np.asarray(theta_deg, dtype=float))
    s, c = np.sin(th), np.cos(th)
    v = n / (np.abs(s) + np.abs(c))
    wz = np.asarray(omega_dps, dtype=float) * DPS_TO_RPM
    vx, vy, wz = np.broadcast_arrays(v * s, -v * c, wz)
    return np.stack([vx, vy, wz], axis=-1)


def twist_to_wheels(twist_rpm, k: float):
    """Inverse kinematics: body twist to the four wheel speeds.

    Parameters
    ----------
    twist_rpm : array_like, shape (..., 3)
        ``(vx, vy, wz)`` in wheel-rpm units [rpm].
    k : float
        ``(lx + ly) / r`` [-].

    Returns
    -------
    ndarray, shape (..., 4)
        Wheel speeds 1..4 [rpm].
    """
    t = np.asarray(twist_rpm, dtype=float)
    scaled = np.stack([t[..., 0], t[..., 1], k * t[..., 2]], axis=-1)
    return scaled @ _IK.T


def wheels_to_twist(wheels_rpm, k: float):
    """Forward kinematics (pseudo-inverse of :func:`twist_to_wheels`).

    Parameters
    ----------
    wheels_rpm : array_like, shape (..., 4)
        Wheel speeds 1..4 [rpm].
    k : float
        ``(lx + ly) / r`` [-].

    Returns
    -------
    ndarray, shape (..., 3)
        ``(vx, vy, wz)`` [rpm], with ``vx`` the mean of the four wheels,
        ``vy = (-w1 + w2 + w3 - w4) / 4`` and ``wz = (-w1 + w2 - w3 + w4) / (4 k)``.
    """
    w = np.asarray(wheels_rpm, dtype=float)
    scaled = w @ _IK / 4.0
    return np.stack([scaled[..., 0], scaled[..., 1], scaled[..., 2] / k], axis=-1)


def command_to_wheels(n_rpm, omega_dps, theta_deg, k: float):
    """Commands straight to wheel speed targets [rpm], shape ``(..., 4)``."""
    return twist_to_wheels(command_to_twist(n_rpm, omega_dps, theta_deg), k)
