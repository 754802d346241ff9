"""Compiled inner loops of the simulator (numba). Pure: arrays in, arrays out.

One robot per outer iteration (``prange``: robots are simulated in parallel); time runs in the
inner loop. Commands are piecewise constant; wheel state is updated with the exact
discretisation of :mod:`mecanum_hil.model.motor`, and the pose with the exact solution for the
body twist averaged over the (sub)step (the SE(2) exponential), so straight runs and pure turns
are exact to rounding.

The steps of :func:`simulate_kernel` are helpers numba inlines into it (``inline="always"``):
each is called per wheel and substep, and a call that is not inlined counts references on its
array arguments, shared by the robots' threads. Measured on the 2-core machine, 256
robots x 5 s at 1 kHz: inlined, 26 / 22 / 13 M robot-steps/s (linear / saturation, rate limit
and deadband / the drive's own dynamics), 18.8 / 18.1 / 11.3 for the one long function before;
with no helper inlined 20 / 18 / 3.9, with only ``_drive_piece`` not inlined 5.4 on the drive.
The price is numba's first compile, once per install (its cache is on disk): 44 s against 34 s
for the one long function and 19 s with no helper inlined.
"""

from __future__ import annotations

import math

import numpy as np

from .._jit import njit, prange
from .discretise import discretise_step

#: Layout of the per-robot state vector used to continue a simulation: y1..y4 [rpm],
#: z1..z4 [rpm s], drive set-points u1..u4 [rpm], then the drive's own dynamics: held
#: controller outputs h1..h4 [rpm/s], lagged drive outputs d1..d4 [rpm/s] and the time to the
#: controller's next tick [s] (0: a tick is due). A 12-wide state (the wheels alone) is accepted
#: by the simulator and padded with zeros.
STATE_WIDTH = 21
#: The first columns: the wheels' PI state and set-points.
WHEEL_STATE_WIDTH = 12

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


@njit(cache=True, inline="always")
def _lag_factors(B, a, ts):
    """``exp(-B ts)``, the integral of ``exp(-B s)`` over ``ts`` and ``exp(-a ts)`` (0 without a
    lag): the same for the four wheels, so computed once per piece."""
    eb = math.exp(-B * ts)
    g = ts if B * ts < 1e-9 else (1.0 - eb) / B  # integral of exp(-B s) over the piece
    ea = math.exp(-a * ts) if a < np.inf else 0.0
    return eb, g, ea


@njit(cache=True, inline="always")
def _lag_pair(y, dl, c, B, a, ts, eb, g, ea):
    """Wheel speed and lagged drive after ``ts`` seconds of held controller output ``c``.

    ``dl' = a (c - dl)`` (``a = 1 / drive_lag_s``; ``a = inf``: no lag, ``dl = c``) and
    ``y' = dl - B y``, solved exactly; ``eb, g, ea`` from :func:`_lag_factors` of ``ts``.
    """
    if not a < np.inf:
        return y * eb + c * g, c
    dl_new = c + (dl - c) * ea
    # integral of exp(-B (ts - s)) (dl - c) exp(-a s) ds
    if abs(a - B) * ts < 1e-7:
        extra = (dl - c) * ts * eb
    else:
        extra = (dl - c) * (ea - eb) / (B - a)
    return y * eb + c * g + extra, dl_new


@njit(cache=True, inline="always")
def _drive_at_rest(per, a, A, C, u, z, h, dl):
    # the drive output a wheel at rest feels: held output, lagged output or PI at y = 0
    if a < np.inf:
        return dl
    if per > 0:
        return h
    return A * u + C * z


@njit(cache=True, inline="always")
def _braking_phase(i, u, ts, A, B, C, per, a, brake, dmax, wu, y, z, hold, dl, q):
    """The part of a piece in which the drive cannot slow wheel ``i`` as fast as the loop asks.

    A wheel whose acceleration towards rest, ``-(c - B y) sign(y)`` with drive output ``c``,
    exceeds ``brake`` [rpm/s] slows at exactly ``brake`` (a drive that coasts instead of
    braking: fast-decay (coasting) PWM, a diode bridge). The phase ends when the wheel reaches
    rest or when the motor's own deceleration has fallen to ``brake``: exactly for a held output
    (controller period, no lag), where that deceleration falls at ``B brake``; to first order in
    the piece otherwise (the drive's rate of change at the phase's start). Advances ``y``,
    ``z``, ``dl`` and ``q`` over the phase; returns its length [s] (0 when the limit is not
    reached). Called only with a finite ``brake``. ``wu``: the output limit ``dmax`` has no
    anti-windup (the integrator integrates while clamped).
    """
    yi = y[i]
    if yi == 0.0:
        return 0.0
    sg = 1.0 if yi > 0.0 else -1.0
    clipped = False
    if a < np.inf:
        c = dl[i]
        cin = hold[i] if per > 0 else A * (u - yi) + C * z[i]
        clipped = per <= 0 and (cin > dmax or cin < -dmax)
        cin = min(max(cin, -dmax), dmax)
        rate = sg * a * (cin - c)  # the lagged drive's rate of change, towards the wheel's sign
    elif per > 0:
        c = hold[i]
        cin = c
        rate = 0.0
    else:
        c = A * (u - yi) + C * z[i]
        clipped = c > dmax or c < -dmax
        c = min(max(c, -dmax), dmax)
        cin = c
        rate = 0.0 if clipped else A * brake + sg * C * (u - yi)
    excess = -brake - sg * (c - B * yi)  # > 0: the loop asks for more braking than there is
    if excess <= 0.0:
        return 0.0
    t_l = abs(yi) / brake  # until the wheel is at rest
    at_rest = True
    rate += B * brake
    if rate > 0.0 and excess / rate < t_l:
        t_l = excess / rate
        at_rest = False
    if t_l > ts:
        t_l = ts
        at_rest = False
    y_new = 0.0 if at_rest else yi - sg * brake * t_l
    q[i] += (yi - 0.5 * sg * brake * t_l) * t_l
    if per <= 0 and (wu or not clipped or (cin > 0) != (u - yi > 0)):
        z[i] += (u - yi) * t_l + 0.5 * sg * brake * t_l * t_l
    if a < np.inf:
        dl[i] = cin + (dl[i] - cin) * math.exp(-a * t_l)
    y[i] = y_new
    return t_l


@njit(cache=True)
def holding_drive(B, u0, no_load, y, fric):
    """The loop output [rpm/s] that holds a wheel at ``y`` [rpm] in steady state: ``B y``
    plus a Coulomb friction ``fric`` [rpm/s] against the motion, or through a fast-decay drive
    (``u0`` finite) the push that balances friction and the pole, less the friction:
    ``sign(y) ((u0 + B |y|) / (1 - |y| / no_load) - u0)`` (the droop held at 1e-3 of the full
    push at or beyond the no-load speed)."""
    if not u0 < np.inf:
        if y == 0.0:
            return 0.0
        return B * y + (fric if y > 0.0 else -fric)
    droop = max(1.0 - abs(y) / no_load, 1e-3)
    push = (u0 + B * abs(y)) / droop - u0
    return push if y >= 0.0 else -push


@njit(cache=True, inline="always")
def _fast_decay_run(v, f, k, t):
    """Speed magnitude [rpm] and its integral [rpm s] after ``t`` seconds of ``v' = f - k v``."""
    if k * t < 1e-12:
        return v + f * t, v * t + 0.5 * f * t * t
    e = -math.expm1(-k * t)  # 1 - exp(-k t)
    v_ss = f / k
    return v_ss + (v - v_ss) * (1.0 - e), v_ss * t + (v - v_ss) * e / k


@njit(cache=True, inline="always")
def _fast_decay_rates(yi, c, B, u0, iy0):
    """The fast-decay drive's equation at speed ``yi`` [rpm] with loop output ``c`` [rpm/s]:
    the direction of motion ``s`` (of ``c`` at rest), and ``f``, ``k`` of ``|y|' = f - k |y|``
    (``f = d - u0`` with the duty's push ``d = max(s c + u0, 0)``, ``k = B + d iy0``)."""
    if yi != 0.0:
        s = 1.0 if yi > 0.0 else -1.0
    else:
        s = 1.0 if c >= 0.0 else -1.0
    d = max(s * c + u0, 0.0)
    return s, max(s * c, -u0), B + d * iy0  # max(s c, -u0) = d - u0, exact for a large u0


@njit(cache=True, inline="always")
def _fast_decay_move(yi, c, rem, B, u0, iy0, brk):
    """Wheel speed [rpm] after ``rem`` seconds of a held loop output ``c`` [rpm/s] through the
    fast-decay drive of :func:`_fast_decay_piece`, and the speed's integral [rpm s]: exact."""
    v = abs(yi)
    if v == 0.0 and abs(c) <= brk:
        return 0.0, 0.0  # held by static friction
    s, f, k = _fast_decay_rates(yi, c, B, u0, iy0)
    v_new, area = _fast_decay_run(v, f, k, rem)
    if v_new >= 0.0:
        return s * v_new, s * area
    # at rest within the piece (only while coasting, f < 0): when, then on in the direction of
    # c, or held there
    if k * rem < 1e-12:
        t0 = v / -f
    else:
        t0 = math.log1p(-v * k / f) / k  # v_ss + (v - v_ss) exp(-k t0) = 0
    t0 = min(max(t0, 0.0), rem)
    area = s * _fast_decay_run(v, f, k, t0)[1]
    if abs(c) <= brk:
        return 0.0, area
    s, f, k = _fast_decay_rates(0.0, c, B, u0, iy0)
    v_new, a1 = _fast_decay_run(0.0, f, k, rem - t0)
    return s * v_new, area + s * a1


@njit(cache=True, inline="always")
def _fast_decay_piece(i, u, rem, A, B, C, per, a, brk, dmax, wu, u0, iy0, y, z, hold, dl,
                      q):
    """Advance wheel ``i`` over ``rem`` seconds through a fast-decay (coasting) PWM drive.

    The loop's output ``c`` [rpm/s] (held, lagged or the continuous PI's, limited to ``dmax``)
    is the duty's push ``d`` less a Coulomb friction ``u0`` [rpm/s]. The push acts only in the
    wheel's direction of motion ``s`` and falls with speed as the back-EMF rises:
    ``s y' = max(s c + u0, 0) (1 - |y| iy0) - u0 - B |y|`` (``iy0 = 1 / no_load_rpm``). A duty
    that would oppose the motion is off and the wheel coasts; at rest it starts in the
    direction of ``c``. For a held output (controller period) the piece is exact. The
    continuous PI's output is held over the piece at its middle, predicted from a first pass
    (second order in the piece); a lagged drive's output is its mean over the piece. A wheel
    that coasts to rest while ``|c|`` is within ``brk`` stays there.
    """
    yi = y[i]
    zi = z[i]
    clipped = False
    if per > 0:
        c = hold[i]
    else:
        # the continuous PI at the piece's middle: its integral half a piece on, the speed
        # the piece's mean (a first pass at the output the piece starts with)
        e = u - yi
        c = min(max(A * e + C * zi, -dmax), dmax)
        if a == np.inf:
            _, area = _fast_decay_move(yi, c, rem, B, u0, iy0, brk)
            e = u - area / rem
        c = A * e + C * (zi + 0.5 * e * rem)
        clipped = c > dmax or c < -dmax
        c = min(max(c, -dmax), dmax)
    cin = c  # the controller's (clipped) output, before the lag
    if a < np.inf:
        ea = math.exp(-a * rem)
        c = dl[i] if a * rem < 1e-12 else \
            cin + (dl[i] - cin) * (-math.expm1(-a * rem)) / (a * rem)
        dl[i] = cin + (dl[i] - cin) * ea
    y_new, area = _fast_decay_move(yi, c, rem, B, u0, iy0, brk)
    q[i] += area
    # anti-windup on the controller's output (unless ``wu``), as the other paths
    if per <= 0 and (wu or not clipped or (cin > 0) != (u - yi > 0)):
        zi += u * rem - area
    y[i] = y_new
    z[i] = zi


@njit(cache=True, inline="always")
def _coast_piece(i, ts, B, a, brk, fric, u0, y, z, hold, dl, q):
    """Advance wheel ``i`` over ``ts`` seconds with its drive off (a drive deadband): no
    output, the integrator cleared, a lagged output decaying; the wheel slows by its pole and a
    Coulomb friction (``fric``, or a fast-decay drive's ``u0``), exactly while its sign holds,
    and stops at rest."""
    yi = y[i]
    z[i] = 0.0
    eb, g, ea = _lag_factors(B, a, ts)
    f = u0 if u0 < np.inf else fric
    y_new, dl_new = _lag_pair(yi, dl[i], 0.0, B, a, ts, eb, g, ea)
    if yi != 0.0 and f > 0.0:
        y_new -= (f if yi > 0.0 else -f) * g
    if yi != 0.0 and y_new * yi <= 0.0 and abs(dl_new) <= brk:
        y_new = 0.0  # at rest, with nothing left to move it
    elif yi == 0.0 and abs(dl_new) <= brk:
        y_new = 0.0
    q[i] += 0.5 * (yi + y_new) * ts
    y[i] = y_new
    dl[i] = dl_new
    hold[i] = 0.0


@njit(cache=True, inline="always")
def _drive_piece(i, u, ts, A, B, C, per, a, brk, fric, brake, dmax, wu, u0, iy0, y, z, hold,
                 dl, tab, q, eb, g, ea):
    """Advance wheel ``i`` over ``ts`` seconds on the path of the drive's own dynamics.

    Between controller ticks (``per > 0``) the held output drives the motor exactly; a
    continuous PI (``per == 0``) without lag is advanced exactly too (``tab`` is its
    discretisation over ``ts`` when ``ts`` is a whole sub-step, recomputed otherwise); a
    continuous PI with a lag holds its output over the piece (first order in the piece). A
    wheel at rest with ``brk > 0`` stays at rest until the drive's magnitude exceeds ``brk``,
    at the instant it does (found in closed form, so the model is smooth in ``brk``). A wheel
    the loop would slow faster than ``brake`` [rpm/s] slows at ``brake`` first
    (:func:`_braking_phase`). With a fast-decay drive (``u0`` finite, see
    :func:`_fast_decay_piece`) the wheel moves by that once it has left rest (never with a
    braking limit: the two are not in one model). Accumulates the integral of the
    speed over the piece into ``q[i]``. ``eb, g, ea``: :func:`_lag_factors` of ``ts`` (when the
    path needs them). ``wu``: the output limit ``dmax`` has no anti-windup. ``fric`` [rpm/s]: a
    Coulomb friction against the motion (``y' = c - B y - fric sign(y)``; callers pass
    ``brk >= fric``): exact while the sign holds, on the closed-form path as a shift of the
    integrator by ``fric / C``; a wheel that passes through rest within the piece keeps the
    friction's sign for the rest of it (first order in the piece), unless it sticks. A NaN
    set-point ``u`` is a drive that is off (:func:`_coast_piece`).
    """
    if u != u:
        _coast_piece(i, ts, B, a, brk, fric, u0, y, z, hold, dl, q)
        return
    rem = ts
    if brake < np.inf:
        rem = ts - _braking_phase(i, u, ts, A, B, C, per, a, brake, dmax, wu, y, z, hold, dl,
                                  q)
        if rem <= 1e-12:
            return
    yi = y[i]
    if brk > 0.0 and yi == 0.0:
        # stuck: find when the drive leaves [-brk, brk] within the piece
        d0 = _drive_at_rest(per, a, A, C, u, z[i], hold[i], dl[i])
        if a < np.inf:
            c = hold[i] if per > 0 else A * u + C * z[i]
            if c > dmax:
                c = dmax
            elif c < -dmax:
                c = -dmax
            if abs(d0) > brk:
                t_go = 0.0
            elif abs(c) > brk:
                sg = 1.0 if c > 0 else -1.0
                # dl(t) = c + (d0 - c) exp(-a t) reaches sg * brk
                t_go = -math.log((sg * brk - c) / (d0 - c)) / a
            else:
                t_go = np.inf
        elif per > 0:
            t_go = 0.0 if abs(d0) > brk else np.inf
        else:
            # at rest the PI output grows linearly: A u + C (z + u t)
            if abs(d0) > brk:
                t_go = 0.0
            elif C * u != 0.0:
                sg = 1.0 if u > 0 else -1.0
                t_go = (sg * brk - d0) / (C * u)
                if t_go < 0:
                    t_go = np.inf
            else:
                t_go = np.inf
        t_rest = min(t_go, rem)
        if t_rest > 0:
            if per <= 0:
                z[i] += u * t_rest
            if a < np.inf:
                c = hold[i] if per > 0 else A * u + C * z[i]
                c = min(max(c, -dmax), dmax)
                dl[i] = c + (dl[i] - c) * math.exp(-a * t_rest)
            rem -= t_rest
            if rem <= 1e-12:
                return
    # moving
    if u0 < np.inf:
        _fast_decay_piece(i, u, rem, A, B, C, per, a, brk, dmax, wu, u0, iy0, y, z, hold, dl,
                          q)
        return
    if rem != ts:
        eb, g, ea = _lag_factors(B, a, rem)
    zi = z[i]
    f = 0.0
    if fric > 0.0:
        if yi != 0.0:
            f = fric if yi > 0.0 else -fric
        else:  # just broken away: the friction opposes the drive that moved it
            f = fric if _drive_at_rest(per, a, A, C, u, zi, hold[i], dl[i]) > 0.0 else -fric
    if per <= 0 and not a < np.inf:
        c = A * (u - yi) + C * zi
        if c > dmax or c < -dmax:
            sg = 1.0 if c > 0 else -1.0
            y_new, _ = _lag_pair(yi, 0.0, sg * dmax, B, np.inf, rem, eb, g, ea)
            y_new -= f * g
            if wu:  # no anti-windup: the integrator follows the error while clamped
                zi += (u - 0.5 * (yi + y_new)) * rem
            elif sg * (u - yi) < 0:
                zi += (u - yi) * rem
        else:
            if rem != tab[10]:
                _discretise_into(A, B, C, rem, tab)
            y_new = tab[0] * yi + tab[1] * zi + tab[4] * u
            q[i] += tab[6] * yi + tab[7] * zi + tab[8] * u
            zi = tab[2] * yi + tab[3] * zi + tab[5] * u
            if f != 0.0:
                # the friction is the integrator shifted by f / C: a21 = -a12 / C, and
                # (1 - a22) / C = cq2 / C, which keeps its digits as C -> 0
                y_new += tab[2] * f
                shift = tab[7] / C * f
                q[i] -= shift
                zi += shift
            _stick(i, y_new, yi, brk, per, a, A, C, u, zi, hold, dl, y, z)
            return
    else:
        if per > 0:
            c = hold[i]
            clipped = False
        else:
            c = A * (u - yi) + C * zi
            clipped = c > dmax or c < -dmax
            c = min(max(c, -dmax), dmax)
        y_new, dl[i] = _lag_pair(yi, dl[i], c, B, a, rem, eb, g, ea)
        y_new -= f * g
        if per <= 0 and (wu or not clipped or (c > 0) != (u - yi > 0)):
            zi += (u - 0.5 * (yi + y_new)) * rem
    q[i] += 0.5 * (yi + y_new) * rem
    _stick(i, y_new, yi, brk, per, a, A, C, u, zi, hold, dl, y, z)


@njit(cache=True, inline="always")
def _stick(i, y_new, y_old, brk, per, a, A, C, u, zi, hold, dl, y, z):
    # a wheel that reaches rest while the drive cannot break it away sticks there
    if brk > 0.0 and y_old != 0.0 and y_new * y_old <= 0.0 and \
            abs(_drive_at_rest(per, a, A, C, u, zi, hold[i], dl[i])) <= brk:
        y_new = 0.0
    y[i] = y_new
    z[i] = zi


@njit(cache=True)
def _discretise_into(A, B, C, h, out):
    discretise_step(A, B, C, h, out)
    out[10] = h


@njit(cache=True, inline="always")
def _controller_tick(u, per, A, C, dmax, wu, y, z, hold):
    # the sampled PI: integral summed over the period, output held until the next tick; with
    # ``wu`` (no anti-windup) the integral is summed while the output is clamped too
    for i in range(4):
        if u[i] != u[i]:  # the drive is off: no output, the integral cleared
            hold[i] = 0.0
            z[i] = 0.0
            continue
        e = u[i] - y[i]
        zn = z[i] + e * per
        c = A * e + C * zn
        if c > dmax or c < -dmax:
            sg = 1.0 if c > 0 else -1.0
            c = sg * dmax
            if wu or sg * e < 0:  # anti-windup: integrate only while the error pulls out
                z[i] = zn
        else:
            z[i] = zn
        hold[i] = c


@njit(cache=True, inline="always")
def _load_state(state, r, y, z, ue, hold, dl):
    """Unpack row ``r`` of ``state`` (see ``STATE_WIDTH``) into the wheels' and the drive's
    arrays; returns the time to the controller's next tick [s]."""
    for i in range(4):
        y[i] = state[r, i]
        z[i] = state[r, 4 + i]
        ue[i] = state[r, 8 + i]
        hold[i] = state[r, 12 + i]
        dl[i] = state[r, 16 + i]
    return state[r, 20]


@njit(cache=True, inline="always")
def _store_state(state_out, r, y, z, ue, hold, dl, until_tick):
    """Pack the wheels' and the drive's arrays into row ``r`` of ``state_out``."""
    for i in range(4):
        state_out[r, i] = y[i]
        state_out[r, 4 + i] = z[i]
        state_out[r, 8 + i] = ue[i]
        state_out[r, 12 + i] = hold[i]
        state_out[r, 16 + i] = dl[i]
    state_out[r, 20] = until_tick


@njit(cache=True, inline="always")
def _record_sample(wheels_out, pose_out, r, t, y, X, Y, phi, active, with_pose):
    """Write robot ``r``'s wheel speeds [rpm] and pose (``phi`` [rad] as [deg]) at sample ``t``:
    NaN for a wheel not ``active`` and, without ``with_pose``, for the pose."""
    for i in range(4):
        wheels_out[r, t, i] = y[i] if active[i] else np.nan
    if with_pose:
        pose_out[r, t, 0] = X
        pose_out[r, t, 1] = Y
        pose_out[r, t, 2] = math.degrees(phi)
    else:
        pose_out[r, t, 0] = np.nan
        pose_out[r, t, 1] = np.nan
        pose_out[r, t, 2] = np.nan


@njit(cache=True, inline="always")
def _wheel_targets(n, w, th, k, db, dboff, gains, tgt):
    """Wheel targets [rpm] of the command ``(n [rpm], w [deg/s], th [deg])`` into ``tgt``:
    inverse kinematics, then deadband ``db`` [rpm] and the wheel ``gains`` (4,). A target
    below the drive deadband ``dboff`` [rpm] is NaN: that wheel's drive is off."""
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
        if abs(tgt[i]) < dboff:
            tgt[i] = np.nan
        elif abs(tgt[i]) < db:
            tgt[i] = 0.0
        tgt[i] *= gains[i]


@njit(cache=True, inline="always")
def _ramp_setpoints(tgt, ue, ub, ramping, rl, hs):
    """Set-points ``ub`` [rpm] the four drives hold over a sub-step of ``hs`` seconds towards
    the targets ``tgt``: with a rate limit ``rl`` [rpm/s] the ramp's mean (second order in the
    step). Advances the ramps' ends ``ue``. A drive that is off (a NaN target) holds NaN, and
    its ramp starts again from 0."""
    for i in range(4):
        u = tgt[i]
        if u != u:
            ue[i] = 0.0
            ub[i] = u
            continue
        if ramping:
            d = u - ue[i]
            lim = rl * hs
            if d > lim:
                d = lim
            elif d < -lim:
                d = -lim
            u = ue[i] + 0.5 * d
            ue[i] += d
        else:
            ue[i] = u
        ub[i] = u


@njit(cache=True, inline="always")
def _closed_form_substep(tgt, ue, ub, y, z, q, coef, ramping, rl, saturating, A, B, C,
                         drive_max, top, wu, active):
    """Advance the four wheels over one sub-step on the closed-form path.

    ``coef``: the sub-step's row of the kernel's ``table`` (its exact discretisation). A wheel
    whose drive is at the saturation limit moves exactly towards ``top`` [rpm] instead, its
    integrator frozen while the error pushes further (anti-windup), or, with ``wu``, integrating
    the error all along (no anti-windup). Writes the integral of each wheel's speed over the
    sub-step into ``q`` [rpm s]. Wheels not ``active`` stay as they are.
    """
    a11 = coef[0]
    a12 = coef[1]
    a21 = coef[2]
    a22 = coef[3]
    b1 = coef[4]
    b2 = coef[5]
    cq1 = coef[6]
    cq2 = coef[7]
    dq = coef[8]
    eb = coef[9]
    hs = coef[10]
    _ramp_setpoints(tgt, ue, ub, ramping, rl, hs)
    for i in range(4):
        if not active[i]:
            continue
        u = ub[i]
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
                if wu:  # no anti-windup: the exact integral of the error over the sub-step
                    z[i] = zi + u * hs - q[i]
                elif sg * (u - yi) < 0:  # anti-windup: integrate only while the error pulls out
                    z[i] = zi + (u - yi) * hs
                continue
        q[i] = cq1 * yi + cq2 * zi + dq * u
        y[i] = a11 * yi + a12 * zi + b1 * u
        z[i] = a21 * yi + a22 * zi + b2 * u


@njit(cache=True, inline="always")
def _drive_dynamics_substep(tgt, ue, ub, y, z, hold, dl, q, tab, coef, until_tick, ramping, rl,
                            saturating, per, a_lag, brk, fric, brake, u0, iy0, A, B, C, dmax, wu,
                            active):
    """Advance the four wheels over one sub-step on the path of the drive's own dynamics.

    The sub-step is cut into pieces that end at the controller's ticks (period ``per`` [s]),
    each advanced by :func:`_drive_piece`. ``coef``: the sub-step's row of the kernel's
    ``table``; ``tab``: scratch (11,). Writes the integral of each wheel's speed over the
    sub-step into ``q`` [rpm s]; returns the time to the next tick [s]. Wheels not ``active``
    stay as they are.
    """
    hs = coef[10]
    _ramp_setpoints(tgt, ue, ub, ramping, rl, hs)
    for i in range(4):
        q[i] = 0.0
    for j in range(10):
        tab[j] = coef[j]
    tab[10] = hs
    rem = hs
    while rem > 1e-12:
        if per > 0 and until_tick <= 1e-12:
            _controller_tick(ub, per, A, C, dmax, wu, y, z, hold)
            until_tick = per
        piece = min(rem, until_tick) if per > 0 else rem
        if u0 == np.inf and (per > 0 or a_lag < np.inf or saturating):
            eb_p, g_p, ea_p = _lag_factors(B, a_lag, piece)
        else:  # the closed-form PI path (tab) and a fast-decay drive need none
            eb_p = g_p = ea_p = 0.0
        for i in range(4):
            if active[i]:
                _drive_piece(i, ub[i], piece, A, B, C, per, a_lag, brk, fric, brake, dmax, wu,
                             u0, iy0, y, z, hold, dl, tab, q, eb_p, g_p, ea_p)
        rem -= piece
        if per > 0:
            until_tick -= piece
    return until_tick


@njit(cache=True, inline="always")
def _advance_pose(q, ex, ey, ez, k, lin, X, Y, phi, cph, sph):
    """Pose after a sub-step whose wheel-speed integrals are ``q`` [rpm s]: the body twist
    averaged over it (times the efficiencies), then the SE(2) exponential. ``cph, sph``: cos and
    sin of ``phi`` [rad], carried along; ``lin``: metres per (rpm s)."""
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
    return X, Y, phi, cph, sph


@njit(cache=True, parallel=True)
def simulate_kernel(
    commands, didx, nsub, table, coeffs, k, wheel_radius_m,
    deadband, gains, top_speed, rate_limit, efficiency, dyn,
    state, pose0, active, with_pose, record, wheels_out, pose_out, state_out, pose_final,
):
    """Simulate N robots over T grid points: the S samples, refined at a dead time's delayed
    command changes (``T == S`` without one).

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
    dyn : (N, 9) float64
        The drive's own dynamics: ``controller_period_s`` [s], ``drive_lag_s`` [s],
        ``breakaway_rpm_per_s`` [rpm/s] (0 when absent), ``braking_limit_rpm_per_s`` [rpm/s]
        (inf when absent), the fast-decay drive's ``coast_decel_rpm_per_s`` [rpm/s] and
        ``no_load_rpm`` [rpm] (inf when absent), 1 where the output limit ``top_speed``
        has no anti-windup (``windup``), else 0, ``friction_rpm_per_s`` [rpm/s] (0 when
        absent) and ``drive_deadband_rpm`` [rpm] (0 when absent).
    state : (N, 21) float64
        Initial wheel state (see ``STATE_WIDTH``).
    pose0 : (N, 3) float64
        Initial pose ``(X [m], Y [m], phi [deg])``.
    active : (4,) bool
        The wheels to simulate: the others stay in their initial state and are written NaN.
    with_pose : bool
        Whether to compute the pose (needs all four wheels ``active``); without, the pose is
        written NaN (``pose_final`` too). A fit of wheel speeds needs only the measured wheels,
        and no pose.
    record : (T,) int64
        The output row of each step's start (``-1``: not written): a grid refined at a dead
        time's delayed command changes writes only its samples.
    wheels_out : (N, S, 4); pose_out : (N, S, 3)
        Wheel speeds [rpm] and pose at each recorded sample (written).
    state_out : (N, 21); pose_final : (N, 3)
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
        hold = np.empty(4)
        dl = np.empty(4)
        ub = np.empty(4)
        tab = np.empty(11)
        until_tick = _load_state(state, r, y, z, ue, hold, dl)
        per = dyn[r, 0]
        lag = dyn[r, 1]
        a_lag = 1.0 / lag if lag > 0 else np.inf
        fric = dyn[r, 7]
        brk = max(dyn[r, 2], fric)  # a wheel at rest needs at least the friction to move
        brake = dyn[r, 3]
        u0 = dyn[r, 4]
        iy0 = 1.0 / dyn[r, 5]
        wu = dyn[r, 6] > 0.0
        dboff = dyn[r, 8]
        dynamics = per > 0 or lag > 0 or brk > 0 or brake < np.inf or u0 < np.inf or dboff > 0
        X = pose0[r, 0]
        Y = pose0[r, 1]
        phi = math.radians(pose0[r, 2])
        cph = math.cos(phi)
        sph = math.sin(phi)
        A = coeffs[r, 0]
        B = coeffs[r, 1]
        C = coeffs[r, 2]
        top = top_speed[r]
        saturating = top < np.inf
        drive_max = B * top if saturating else np.inf
        dmax = drive_max
        rl = rate_limit[r]
        ramping = rl < np.inf
        ex = efficiency[r, 0]
        ey = efficiency[r, 1]
        ez = efficiency[r, 2]
        last_n = np.nan
        last_w = np.nan
        last_th = np.nan
        for t in range(T):
            if record[t] >= 0:
                _record_sample(wheels_out, pose_out, r, record[t], y, X, Y, phi, active,
                               with_pose)
            if t == T - 1:
                break
            n = commands[r, t, 0]
            w = commands[r, t, 1]
            th = commands[r, t, 2]
            if n != last_n or w != last_w or th != last_th:
                last_n = n
                last_w = w
                last_th = th
                _wheel_targets(n, w, th, k, deadband[r], dboff, gains[r], tgt)
            coef = table[r, didx[t]]
            for _ in range(nsub[t]):
                if dynamics:
                    until_tick = _drive_dynamics_substep(
                        tgt, ue, ub, y, z, hold, dl, q, tab, coef, until_tick, ramping, rl,
                        saturating, per, a_lag, brk, fric, brake, u0, iy0, A, B, C, dmax, wu,
                        active)
                else:
                    _closed_form_substep(tgt, ue, ub, y, z, q, coef, ramping, rl, saturating,
                                         A, B, C, drive_max, top, wu, active)
                if with_pose:
                    X, Y, phi, cph, sph = _advance_pose(q, ex, ey, ez, k, lin, X, Y, phi, cph,
                                                        sph)
        _store_state(state_out, r, y, z, ue, hold, dl, until_tick)
        pose_final[r, 0] = X if with_pose else np.nan
        pose_final[r, 1] = Y if with_pose else np.nan
        pose_final[r, 2] = math.degrees(phi) if with_pose else np.nan
