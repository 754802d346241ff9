"""A fine explicit-Euler reference of one wheel's PI loop around the first-order motor, with a
Coulomb friction and a drive deadband, for the tests of the simulator's closed forms."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def pi_loop_euler(A: float, B: float, C: float, t_out: np.ndarray,
                  targets: Callable[[np.ndarray], np.ndarray], fric: float = 0.0,
                  drive_deadband: float = 0.0, dt: float = 2e-6) -> np.ndarray:
    """Wheel speed [rpm] at ``t_out`` [s] of ``y' = c - B y - fric sign(y)``, the drive
    ``c = A (u - y) + C z``, ``z' = u - y``, for the targets ``targets(t)`` [rpm].

    A wheel at rest stays there while the drive is within the friction, and one that reaches
    rest while it is, sticks. Below ``drive_deadband`` the drive is off: no output, the
    integral cleared, the wheel coasting.
    """
    y = z = 0.0
    ts = np.arange(0.0, t_out[-1] + dt / 2, dt)
    us = targets(ts)
    out = np.empty(ts.size)
    for k in range(ts.size):
        out[k] = y
        u = us[k]
        off = abs(u) < drive_deadband
        if off:
            z = 0.0
        c = 0.0 if off else A * (u - y) + C * z
        if y == 0.0 and abs(c) <= fric:
            z += 0.0 if off else u * dt
            continue
        sign = np.sign(y) if y != 0.0 else np.sign(c)
        y_new = y + (c - B * y - fric * sign) * dt
        if y != 0.0 and y_new * y <= 0.0 and (off or abs(A * u + C * z) <= fric):
            y_new = 0.0
        z += 0.0 if off else (u - y) * dt
        y = y_new
    return np.interp(t_out, ts, out)
