"""Compiled inner loops of the simulator (numba). Pure: arrays in, arrays out.

One robot per outer iteration (``prange``: robots are simulated in parallel); time runs in the
inner loop. Commands are piecewise constant; wheel state is updated with the exact
discretisation of :mod:`mecanum_hil.model.motor`, and the pose with the exact solution for the
body twist averaged over the (sub)step (the SE(2) exponential), so straight runs and pure turns
are exact to rounding.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

#: Layout of the per-robot state vector used to continue a simulation.
STATE_WIDTH = 12  # y1..y4 [rpm], z1..z4 [rpm s], drive set-points u1..u4 [rpm]

_RPM_S_TO_RAD = 2.0 * math.pi / 60.0


@njit(cache=True, inline="always")
def _exp_se2(a):
    # sin(a)/a, (1 - cos a)/a, cos a, sin a for the heading increment a [rad]
    if abs(a) < 0.05:
        a2 = a * a
        s_over = 1.0 - a2 / 6.0 * (1.0 - a2 / 20.0 * (1.0 - a2 / 42.0 * (1.0 - a2 / 72.0)))
        c_over = a / 2.0 * (1.0 - a2 / 12.0 * (1.0 - a2 / 30.0 * (1.0 - a2 / 56.0)))
        ca = 1.0 - a2 / 2.0 * (1.0 - a2 / 12.0 * (1.0 - a2 / 30.0 * (1.0 - a2 / 56.0)))
        sa = a * s_over
        return s_over, c_over, ca, sa
    sa = math.sin(a)
    ca = math.cos(a)
    return sa / a, (1.0 - ca) / a, ca, sa


@njit(cache=True, parallel=True)
def simulate_kernel(
    commands, didx, nsub, table, coeffs, k, wheel_radius_m,
    deadband, gains, top_speed, rate_limit, efficiency,
    state, pose0, wheels_out, pose_out, state_out, pose_final,
):
    """Simulate N robots over T samples.

    Parameters
    ----------
    commands : (N, T, 3) float64
        ``(n [rpm], omega [deg/s], theta [deg])`` in force from sample t to t + 1.
    didx : (T,) int64
        Row of ``table`` to use for the step after sample t.
    nsub : (T,) int64
        Number of sub-steps of that step (1 on the closed-form path).
    table : (N, K, 11) float64
        Discretisations (see :func:`mecanum_hil.model.motor.discretise`) for the sub-step lengths.
    coeffs : (N, 3) float64
        ``(A, B, C)`` per robot.
    k, wheel_radius_m : float
        Kinematic constant ``(lx + ly) / r`` [-] and wheel radius [m].
    deadband, top_speed, rate_limit : (N,) float64
        Effect parameters (0, inf and inf when absent); ``rate_limit`` in [rpm/s].
    gains : (N, 4) float64;  efficiency : (N, 3) float64
    state : (N, 12) float64
        Initial wheel state (see ``STATE_WIDTH``).
    pose0 : (N, 3) float64
        Initial pose ``(X [m], Y [m], phi [deg])``.
    wheels_out : (N, T, 4); pose_out : (N, T, 3)
        Wheel speeds [rpm] and pose at each sample (written).
    state_out : (N, 12); pose_final : (N, 3)
        State and pose at the last sample (written).
    """
    N, T, _ = commands.shape
    lin = _RPM_S_TO_RAD * wheel_radius_m  # metres per (rpm s)
    for r in prange(N):
        y = np.empty(4)
        z = np.empty(4)
        ue = np.empty(4)
        tgt = np.empty(4)
        q = np.empty(4)
        for i in range(4):
            y[i] = state[r, i]
            z[i] = state[r, 4 + i]
            ue[i] = state[r, 8 + i]
        X = pose0[r, 0]
        Y = pose0[r, 1]
        phi = math.radians(pose0[r, 2])
        cph = math.cos(phi)
        sph = math.sin(phi)
        A = coeffs[r, 0]
        B = coeffs[r, 1]
        C = coeffs[r, 2]
        db = deadband[r]
        top = top_speed[r]
        saturating = top < np.inf
        drive_max = B * top
        rl = rate_limit[r]
        ramping = rl < np.inf
        ex = efficiency[r, 0]
        ey = efficiency[r, 1]
        ez = efficiency[r, 2]
        last_n = np.nan
        last_w = np.nan
        last_th = np.nan
        for t in range(T):
            for i in range(4):
                wheels_out[r, t, i] = y[i]
            pose_out[r, t, 0] = X
            pose_out[r, t, 1] = Y
            pose_out[r, t, 2] = math.degrees(phi)
            if t == T - 1:
                break
            n = commands[r, t, 0]
            w = commands[r, t, 1]
            th = commands[r, t, 2]
            if n != last_n or w != last_w or th != last_th:
                last_n = n
                last_w = w
                last_th = th
                thr = math.radians(th)
                s = math.sin(thr)
                c = math.cos(thr)
                v = n / (abs(s) + abs(c))
                vx = v * s
                vy = -v * c
                kwz = k * w / 6.0
                tgt[0] = vx - vy - kwz
                tgt[1] = vx + vy + kwz
                tgt[2] = vx + vy - kwz
                tgt[3] = vx - vy + kwz
                for i in range(4):
                    if abs(tgt[i]) < db:
                        tgt[i] = 0.0
                    tgt[i] *= gains[r, i]
            row = didx[t]
            a11 = table[r, row, 0]
            a12 = table[r, row, 1]
            a21 = table[r, row, 2]
            a22 = table[r, row, 3]
            b1 = table[r, row, 4]
            b2 = table[r, row, 5]
            cq1 = table[r, row, 6]
            cq2 = table[r, row, 7]
            dq = table[r, row, 8]
            eb = table[r, row, 9]
            hs = table[r, row, 10]
            for _ in range(nsub[t]):
                for i in range(4):
                    u = tgt[i]
                    if ramping:
                        d = u - ue[i]
                        lim = rl * hs
                        if d > lim:
                            d = lim
                        elif d < -lim:
                            d = -lim
                        # hold the ramp's mean over the sub-step (second order in the step)
                        u = ue[i] + 0.5 * d
                        ue[i] += d
                    else:
                        ue[i] = u
                    yi = y[i]
                    zi = z[i]
                    if saturating:
                        drive = A * (u - yi) + C * zi
                        if drive > drive_max or drive < -drive_max:
                            sg = 1.0 if drive > 0 else -1.0
                            ys = sg * top
                            if B > 0:
                                y[i] = ys + (yi - ys) * eb
                                q[i] = ys * hs + (yi - ys) * (1.0 - eb) / B
                            else:
                                y[i] = yi
                                q[i] = yi * hs
                            # anti-windup: integrate only while the error pulls out of the limit
                            if sg * (u - yi) < 0:
                                z[i] = zi + (u - yi) * hs
                            continue
                    q[i] = cq1 * yi + cq2 * zi + dq * u
                    y[i] = a11 * yi + a12 * zi + b1 * u
                    z[i] = a21 * yi + a22 * zi + b2 * u
                # body twist averaged over the sub-step [rpm s], then the SE(2) exponential
                bvx = 0.25 * (q[0] + q[1] + q[2] + q[3]) * ex
                bvy = 0.25 * (-q[0] + q[1] + q[2] - q[3]) * ey
                bwz = 0.25 * (-q[0] + q[1] - q[2] + q[3]) / k * ez
                a = bwz * _RPM_S_TO_RAD
                so, co, ca, sa = _exp_se2(a)
                dxl = lin * (bvx * so - bvy * co)
                dyl = lin * (bvx * co + bvy * so)
                X += cph * dxl - sph * dyl
                Y += sph * dxl + cph * dyl
                phi += a
                cph, sph = cph * ca - sph * sa, sph * ca + cph * sa
        for i in range(4):
            state_out[r, i] = y[i]
            state_out[r, 4 + i] = z[i]
            state_out[r, 8 + i] = ue[i]
        pose_final[r, 0] = X
        pose_final[r, 1] = Y
        pose_final[r, 2] = math.degrees(phi)
