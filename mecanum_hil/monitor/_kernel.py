"""Compiled per-sample core of shadow mode (numba). No I/O: arrays in, state arrays updated.

One call of :func:`monitor_step` handles one telemetry sample:

1. advance the model exactly from the previous sample time to this one, with the commands in
   force in between (a dead time splits the step at the delayed command changes; saturation and
   rate limit sub-step it at most ``max_substep_s``, exactly as :mod:`mecanum_hil.model.simulate`
   does, so the streamed prediction equals ``simulate`` on the same samples to rounding);
2. form the residuals measured - predicted of every channel measured in this sample;
3. update the noise estimate during warm-up, then the two-sided CUSUM of each channel, and write
   alarm / recovery / noise events into ``events``.

The discretisation of a step is the closed form of the 2x2 matrix exponential (real, repeated or
complex poles), the same matrices :func:`mecanum_hil.model.motor.discretise` computes with
``scipy.linalg.expm``; the closed form costs ~0.1 us, so irregular live sample times cost nothing
extra. Everything per sample happens in this one compiled call: the Python caller only packs the
sample into a row and looks at the returned event count.
"""

from __future__ import annotations

import math

import numpy as np

from .._jit import njit
from ..model._kernels import (
    _controller_tick,
    _drive_piece,
    _exp_se2,
    _fast_decay_rates,
    _lag_factors,
    _ramp_setpoints,
    holding_drive,
)
from ..model.discretise import discretise_step

_RPM_S_TO_RAD = 2.0 * math.pi / 60.0

#: Channels, in this order (recording column names).
CHANNELS = ("wheel1_rpm", "wheel2_rpm", "wheel3_rpm", "wheel4_rpm", "x_m", "y_m", "phi_deg")
N_CH = 7
POSE0 = 4  # first pose channel

# --- parameter vector ``pp`` -------------------------------------------------------------------
P_A, P_B, P_C, P_K, P_R = 0, 1, 2, 3, 4
P_DB = 5
P_GAIN = 6  # 4 values
P_TOP, P_RL = 10, 11
P_EFF = 12  # 3 values
P_DELAY, P_SUB = 15, 16
P_DRIFT, P_THRESH, P_WARM, P_MINN, P_CLEAR, P_PWIN, P_FROM_MEAS = 17, 18, 19, 20, 21, 22, 23
P_NOISE = 24  # 7 given noise levels (0 = estimate)
P_FLOOR = 31  # 7 noise floors
P_CMD0 = 38  # 3 values: command in force before the first sample (start from rest)
P_TOL = 41  # timing tolerance [s]
P_SAFETY = 42  # noise estimate margin [standard errors]
P_PER, P_LAG, P_BRK = 43, 44, 45  # the drive's own dynamics (0 when absent)
P_BRAKE = 46  # the braking limit [rpm/s] (inf when absent)
P_U0, P_Y0 = 47, 48  # fast-decay drive: coasting deceleration [rpm/s], no-load speed [rpm]
P_WINDUP = 49  # 1 where the output limit P_TOP has no anti-windup (``windup``), else 0
P_FRIC = 50  # Coulomb friction [rpm/s] (0 when absent)
P_DBOFF = 51  # drive deadband [rpm] (0 when absent): below it the drive is off
P_WIDTH = 52

# --- float state ``fs`` ------------------------------------------------------------------------
S_Y, S_Z, S_UE, S_TGT = 0, 4, 8, 12  # 4 values each
S_CUR = 16  # delayed command in force (3)
S_TPREV, S_TSTART = 22, 23
S_PX, S_PY, S_PPHI = 24, 25, 26  # model pose, phi in rad
S_TANCH, S_HAVE_ANCH = 27, 28
S_PRED = 29  # predicted value of each channel at the last sample (7)
S_MEAS = 36  # measured value (7)
S_HOLD, S_DL = 43, 47  # held controller outputs, lagged drive outputs (4 each) [rpm/s]
S_UNTIL = 51  # time to the controller's next tick [s] (0: due)
S_WIDTH = 52

# --- per-channel state ``ch`` (N_CH, C_WIDTH) --------------------------------------------------
C_SPOS, C_SNEG, C_SIGMA = 0, 1, 2
C_SUMP, C_NP, C_ONP = 3, 4, 5  # residual sum, count, onset time of the positive run
C_SUMN, C_NN, C_ONN = 6, 7, 8
C_COUNT = 9  # residuals collected for the noise estimate
C_DIVERGED, C_LASTX = 10, 11  # alarm latched, time of the last threshold crossing
C_RESID = 12  # last residual
C_WIDTH = 13

# --- events ``ev`` (max rows, E_WIDTH) ---------------------------------------------------------
EV_ALARM, EV_RECOVERED, EV_NOISE = 1.0, 2.0, 3.0
E_KIND, E_CH, E_T, E_RESID, E_ONSET, E_DIR, E_STAT, E_SIGMA, E_PRED, E_MEAS = range(10)
E_WIDTH = 10
MAX_EVENTS = 2 * N_CH

# --- command queue ``queue`` (capacity, 4): t_apply, n, omega, theta; ``qi`` = (head, count)


@njit(cache=True)
def _set_targets(pp, fs):
    n = fs[S_CUR]
    th = math.radians(fs[S_CUR + 2])
    s = math.sin(th)
    c = math.cos(th)
    v = n / (abs(s) + abs(c))
    vx = v * s
    vy = -v * c
    kwz = pp[P_K] * fs[S_CUR + 1] / 6.0
    fs[S_TGT + 0] = vx - vy - kwz
    fs[S_TGT + 1] = vx + vy + kwz
    fs[S_TGT + 2] = vx + vy - kwz
    fs[S_TGT + 3] = vx - vy + kwz
    for i in range(4):
        if abs(fs[S_TGT + i]) < pp[P_DBOFF]:
            fs[S_TGT + i] = np.nan  # the drive is off, as in the simulator's kernel
        elif abs(fs[S_TGT + i]) < pp[P_DB]:
            fs[S_TGT + i] = 0.0
        fs[S_TGT + i] *= pp[P_GAIN + i]


@njit(cache=True)
def _advance_piece(pp, fs, h, tab, q):
    """Advance wheels and model pose over ``h`` seconds with the targets in ``fs``."""
    top = pp[P_TOP]
    rl = pp[P_RL]
    saturating = top < np.inf
    ramping = rl < np.inf
    per = pp[P_PER]
    dynamics = per > 0 or pp[P_LAG] > 0 or pp[P_BRK] > 0 or pp[P_BRAKE] < np.inf or \
        pp[P_U0] < np.inf or pp[P_FRIC] > 0 or pp[P_DBOFF] > 0
    nsub = 1
    if saturating or ramping or dynamics:
        nsub = max(1, math.ceil(h / pp[P_SUB] - 1e-9))
    hs = h / nsub
    A = pp[P_A]
    B = pp[P_B]
    C = pp[P_C]
    discretise_step(A, B, C, hs, tab)
    tab[10] = hs
    drive_max = B * top if saturating else np.inf
    k = pp[P_K]
    lin = _RPM_S_TO_RAD * pp[P_R]
    for _ in range(nsub):
        if dynamics:
            _drive_substep(pp, fs, hs, tab, q, saturating, ramping, drive_max)
        else:
            for i in range(4):
                u = fs[S_TGT + i]
                if ramping:
                    d = u - fs[S_UE + i]
                    lim = rl * hs
                    if d > lim:
                        d = lim
                    elif d < -lim:
                        d = -lim
                    # the ramp's mean over the sub-step, as the simulator holds it
                    u = fs[S_UE + i] + 0.5 * d
                    fs[S_UE + i] += d
                else:
                    fs[S_UE + i] = u
                yi = fs[S_Y + i]
                zi = fs[S_Z + i]
                if saturating:
                    drive = A * (u - yi) + C * zi
                    if drive > drive_max or drive < -drive_max:
                        sg = 1.0 if drive > 0 else -1.0
                        ys = sg * top
                        if B > 0:
                            fs[S_Y + i] = ys + (yi - ys) * tab[9]
                            q[i] = ys * hs + (yi - ys) * (1.0 - tab[9]) / B
                        else:
                            q[i] = yi * hs
                        # anti-windup or none, as in the simulator
                        if pp[P_WINDUP] > 0:
                            fs[S_Z + i] = zi + u * hs - q[i]
                        elif sg * (u - yi) < 0:
                            fs[S_Z + i] = zi + (u - yi) * hs
                        continue
                q[i] = tab[6] * yi + tab[7] * zi + tab[8] * u
                fs[S_Y + i] = tab[0] * yi + tab[1] * zi + tab[4] * u
                fs[S_Z + i] = tab[2] * yi + tab[3] * zi + tab[5] * u
        bvx = 0.25 * (q[0] + q[1] + q[2] + q[3]) * pp[P_EFF]
        bvy = 0.25 * (-q[0] + q[1] + q[2] - q[3]) * pp[P_EFF + 1]
        bwz = 0.25 * (-q[0] + q[1] - q[2] + q[3]) / k * pp[P_EFF + 2]
        a = bwz * _RPM_S_TO_RAD
        so, co, _, _ = _exp_se2(a)
        dxl = lin * (bvx * so - bvy * co)
        dyl = lin * (bvx * co + bvy * so)
        cph = math.cos(fs[S_PPHI])
        sph = math.sin(fs[S_PPHI])
        fs[S_PX] += cph * dxl - sph * dyl
        fs[S_PY] += sph * dxl + cph * dyl
        fs[S_PPHI] += a


@njit(cache=True)
def _drive_substep(pp, fs, hs, tab, q, saturating, ramping, drive_max):
    """One sub-step of the wheels with the drive's own dynamics (controller period, drive
    lag, breakaway, braking limit, fast decay, friction), exactly as the simulator's kernel
    advances it (pieces end at ticks)."""
    A = pp[P_A]
    B = pp[P_B]
    C = pp[P_C]
    per = pp[P_PER]
    a_lag = 1.0 / pp[P_LAG] if pp[P_LAG] > 0 else np.inf
    fric = pp[P_FRIC]
    brk = max(pp[P_BRK], fric)  # a wheel at rest needs at least the friction to move
    brake = pp[P_BRAKE]
    u0 = pp[P_U0]
    iy0 = 1.0 / pp[P_Y0]
    dmax = drive_max if saturating else np.inf
    wu = pp[P_WINDUP] > 0
    rl = pp[P_RL]
    ub = np.empty(4)
    # the set-points as the simulator ramps them (a drive that is off holds NaN)
    _ramp_setpoints(fs[S_TGT:S_TGT + 4], fs[S_UE:S_UE + 4], ub, ramping, rl, hs)
    for i in range(4):
        q[i] = 0.0
    y = fs[S_Y:S_Y + 4]
    z = fs[S_Z:S_Z + 4]
    hold = fs[S_HOLD:S_HOLD + 4]
    dl = fs[S_DL:S_DL + 4]
    rem = hs
    while rem > 1e-12:
        if per > 0 and fs[S_UNTIL] <= 1e-12:
            _controller_tick(ub, per, A, C, dmax, wu, y, z, hold)
            fs[S_UNTIL] = per
        piece = min(rem, fs[S_UNTIL]) if per > 0 else rem
        if u0 == np.inf and (per > 0 or a_lag < np.inf or saturating):
            eb_p, g_p, ea_p = _lag_factors(B, a_lag, piece)
        else:  # the closed-form PI path and a fast-decay drive need none
            eb_p = g_p = ea_p = 0.0
        for i in range(4):
            _drive_piece(i, ub[i], piece, A, B, C, per, a_lag, brk, fric, brake, dmax, wu, u0,
                         iy0, y, z, hold, dl, tab, q, eb_p, g_p, ea_p)
        rem -= piece
        if per > 0:
            fs[S_UNTIL] -= piece


@njit(cache=True)
def _advance(pp, fs, queue, qi, t, tab, q):
    """Advance from the previous sample time to ``t``, splitting at delayed command changes."""
    tcur = fs[S_TPREV]
    eps = 1e-12 * max(1.0, abs(t))
    cap = queue.shape[0]
    while qi[1] > 0 and queue[qi[0], 0] <= t + eps:
        ta = queue[qi[0], 0]
        if ta > tcur + eps:
            _advance_piece(pp, fs, ta - tcur, tab, q)
            tcur = ta
        for j in range(3):
            fs[S_CUR + j] = queue[qi[0], 1 + j]
        _set_targets(pp, fs)
        qi[0] = (qi[0] + 1) % cap
        qi[1] -= 1
    if t > tcur + eps:
        _advance_piece(pp, fs, t - tcur, tab, q)


@njit(cache=True)
def _cusum(pp, ch, c, r, t, ev, nev):
    """Two-sided CUSUM of channel ``c`` on residual ``r``; returns the new event count."""
    sig = ch[c, C_SIGMA]
    z = r / sig
    k = pp[P_DRIFT]
    sp = ch[c, C_SPOS] + z - k
    if sp > 0.0:
        if ch[c, C_SPOS] == 0.0:
            ch[c, C_SUMP] = 0.0
            ch[c, C_NP] = 0.0
            ch[c, C_ONP] = t
        ch[c, C_SUMP] += r
        ch[c, C_NP] += 1.0
    else:
        sp = 0.0
    sn = ch[c, C_SNEG] - z - k
    if sn > 0.0:
        if ch[c, C_SNEG] == 0.0:
            ch[c, C_SUMN] = 0.0
            ch[c, C_NN] = 0.0
            ch[c, C_ONN] = t
        ch[c, C_SUMN] += r
        ch[c, C_NN] += 1.0
    else:
        sn = 0.0
    ch[c, C_SPOS] = sp
    ch[c, C_SNEG] = sn
    h = pp[P_THRESH]
    if sp > h or sn > h:
        pos = sp >= sn
        if ch[c, C_DIVERGED] == 0.0:
            ev[nev, E_KIND] = EV_ALARM
            ev[nev, E_CH] = c
            ev[nev, E_T] = t
            # the CUSUM's own estimate of the shift: mean residual since the statistic left 0
            ev[nev, E_RESID] = ch[c, C_SUMP] / ch[c, C_NP] if pos else ch[c, C_SUMN] / ch[c, C_NN]
            ev[nev, E_ONSET] = ch[c, C_ONP] if pos else ch[c, C_ONN]
            ev[nev, E_DIR] = 1.0 if pos else -1.0
            ev[nev, E_STAT] = sp if pos else sn
            ev[nev, E_SIGMA] = sig
            nev += 1
            ch[c, C_DIVERGED] = 1.0
        ch[c, C_LASTX] = t
        ch[c, C_SPOS] = 0.0
        ch[c, C_SNEG] = 0.0
    elif ch[c, C_DIVERGED] == 1.0 and t - ch[c, C_LASTX] >= pp[P_CLEAR]:
        ch[c, C_DIVERGED] = 0.0
        ev[nev, E_KIND] = EV_RECOVERED
        ev[nev, E_CH] = c
        ev[nev, E_T] = t
        ev[nev, E_RESID] = r
        ev[nev, E_ONSET] = ch[c, C_LASTX]
        ev[nev, E_SIGMA] = sig
        nev += 1
    return nev


@njit(cache=True)
def _residual(pp, fs, ch, buf, c, raw, r, t, ev, nev):
    """Feed channel ``c``: the raw residual to the noise estimate during warm-up, then the
    (timing-tolerant) residual ``r`` to the CUSUM."""
    ch[c, C_RESID] = r
    if ch[c, C_SIGMA] > 0.0:
        return _cusum(pp, ch, c, r, t, ev, nev)
    n = int(ch[c, C_COUNT])
    buf[c, n] = raw
    n += 1
    ch[c, C_COUNT] = n
    if n >= buf.shape[1] or (n >= pp[P_MINN] and t - fs[S_TSTART] >= pp[P_WARM]):
        x = buf[c, :n]
        mad = np.median(np.abs(x - np.median(x)))
        # the MAD estimate's standard error is ~1.17 sigma / sqrt(n); an underestimate inflates
        # every z and shortens the CUSUM's run length steeply, so take an upper bound
        margin = 1.0 + pp[P_SAFETY] * 1.17 / math.sqrt(n)
        ch[c, C_SIGMA] = max(1.482602218505602 * mad * margin, pp[P_FLOOR + c])
        ev[nev, E_KIND] = EV_NOISE
        ev[nev, E_CH] = c
        ev[nev, E_T] = t
        ev[nev, E_SIGMA] = ch[c, C_SIGMA]
        nev += 1
    return nev


@njit(cache=True)
def _slope(pp, fs, i):
    """Rate of change of the model's wheel ``i`` now [rpm/s] (drive output minus the pole)."""
    y = fs[S_Y + i]
    off = fs[S_TGT + i] != fs[S_TGT + i]  # a drive deadband holds the drive off
    if pp[P_LAG] > 0:
        drive = fs[S_DL + i]
    elif off:
        drive = 0.0
    elif pp[P_PER] > 0:
        drive = fs[S_HOLD + i]
    else:
        drive = pp[P_A] * (fs[S_UE + i] - y) + pp[P_C] * fs[S_Z + i]
        lim = pp[P_B] * pp[P_TOP]
        if drive > lim:
            drive = lim
        elif drive < -lim:
            drive = -lim
    fric = pp[P_FRIC]
    if y == 0.0 and abs(drive) <= max(pp[P_BRK], fric):
        return 0.0  # held by static friction
    u0 = pp[P_U0]
    if off:  # coasting: the pole and the friction (a fast-decay drive's own)
        f = u0 if u0 < np.inf else fric
        return drive - pp[P_B] * y - (f if y > 0.0 else -f if y < 0.0 else 0.0)
    if u0 < np.inf:  # a fast-decay drive: the push along the motion, less friction
        s, f, k = _fast_decay_rates(y, drive, pp[P_B], u0, 1.0 / pp[P_Y0])
        return s * (f - k * abs(y))
    slope = drive - pp[P_B] * y
    if fric > 0.0:  # against the motion, or against the drive that breaks the wheel away
        slope -= fric if (y > 0.0 or (y == 0.0 and drive > 0.0)) else -fric
    brake = pp[P_BRAKE]
    if y > 0.0 and slope < -brake:
        return -brake  # the drive cannot slow the wheel faster
    if y < 0.0 and slope > brake:
        return brake
    return slope


@njit(cache=True)
def _wrap_deg(a):
    return (a + 180.0) % 360.0 - 180.0


@njit(cache=True)
def _start(row, pp, fs):
    """The state at the first sample: commands and wheels from it (or the defaults), at rest
    unless measured, the pose measured or the origin facing +Y."""
    fs[S_TSTART] = row[0]
    start_meas = pp[P_FROM_MEAS] > 0.0
    for j in range(3):
        c0 = row[1 + j] if start_meas and not math.isnan(row[1 + j]) else pp[P_CMD0 + j]
        fs[S_CUR + j] = c0
    _set_targets(pp, fs)
    for i in range(4):
        w = row[4 + i]
        # the drive holding that speed (as the simulator's steady state): B y, or the push
        # of a fast-decay drive that balances friction and the pole there
        hold = 0.0
        if start_meas and not math.isnan(w):
            # steady state at the measured speed: drive A (u - y) + C z = hold with u = y
            hold = holding_drive(pp[P_B], pp[P_U0], pp[P_Y0], w, pp[P_FRIC])
            fs[S_Y + i] = w
            fs[S_Z + i] = hold / pp[P_C]
            fs[S_UE + i] = w
        else:
            fs[S_Y + i] = 0.0
            fs[S_Z + i] = 0.0
            fs[S_UE + i] = 0.0
        fs[S_HOLD + i] = hold
        fs[S_DL + i] = hold
    fs[S_UNTIL] = 0.0
    if not (math.isnan(row[8]) or math.isnan(row[9]) or math.isnan(row[10])):
        fs[S_PX] = row[8]
        fs[S_PY] = row[9]
        fs[S_PPHI] = math.radians(row[10])
    else:
        fs[S_PX] = 0.0
        fs[S_PY] = 0.0
        fs[S_PPHI] = math.radians(90.0)


@njit(cache=True)
def _pose_residuals(row, pp, fs, ch, buf, ev, nev):
    """A measured pose against the model's, once a window has passed since the anchor
    (the first measured pose anchors); returns the events written so far."""
    t = row[0]
    if fs[S_HAVE_ANCH] == 0.0:
        fs[S_HAVE_ANCH] = 1.0
        fs[S_TANCH] = t
        fs[S_PX] = row[8]
        fs[S_PY] = row[9]
        fs[S_PPHI] = math.radians(row[10])
    elif t - fs[S_TANCH] >= pp[P_PWIN] * (1.0 - 1e-9):
        # pose over a window, re-anchored on the measured pose: the open-loop model's
        # dead-reckoning drift cannot build up, and the noise of a window's residual is
        # that of two pose measurements whatever the window's length
        rx = row[8] - fs[S_PX]
        ry = row[9] - fs[S_PY]
        rphi = _wrap_deg(row[10] - math.degrees(fs[S_PPHI]))
        nev = _residual(pp, fs, ch, buf, 4, rx, rx, t, ev, nev)
        nev = _residual(pp, fs, ch, buf, 5, ry, ry, t, ev, nev)
        nev = _residual(pp, fs, ch, buf, 6, rphi, rphi, t, ev, nev)
        fs[S_TANCH] = t
        fs[S_PX] = row[8]
        fs[S_PY] = row[9]
        fs[S_PPHI] = math.radians(row[10])
    return nev


@njit(cache=True)
def monitor_step(row, pp, fs, ch, buf, queue, qi, ev, tab, q):
    """Process one sample ``row = (t, n, omega, theta, w1..w4, x, y, phi)``.

    Returns the number of events written to ``ev`` (0 almost always).
    """
    t = row[0]
    if math.isnan(fs[S_TPREV]):
        _start(row, pp, fs)
    else:
        _advance(pp, fs, queue, qi, t, tab, q)
    fs[S_TPREV] = t
    # queue this sample's command: it acts from t + dead time. Every sample gets an entry, also
    # a repeated command, because the simulator cuts its grid at every delayed sample time and
    # the pose integration (exact for a constant twist only) depends on where steps are cut.
    if not (math.isnan(row[1]) or math.isnan(row[2]) or math.isnan(row[3])):
        cap = queue.shape[0]
        tail = (qi[0] + qi[1]) % cap
        queue[tail, 0] = t + pp[P_DELAY]
        for j in range(3):
            queue[tail, 1 + j] = row[1 + j]
        qi[1] += 1
    # The command queue and the wheel residuals stay inline: as @njit functions of their own
    # (even with inline="always") a replay took 9-16 % longer per row (560-600 vs 630-670 ns,
    # min of 30 runs of 100 000 rows on the 2-core machine under load; the same kernel twice
    # differed by up to +-10 %); the first sample and the pose cost nothing measurable as
    # functions (0.97-1.08), so they are.
    nev = 0
    for i in range(4):
        fs[S_PRED + i] = fs[S_Y + i]
        fs[S_MEAS + i] = row[4 + i]
        if not math.isnan(row[4 + i]):
            r = row[4 + i] - fs[S_Y + i]
            raw = r
            if pp[P_TOL] > 0.0:
                # a measurement the model reaches within +-tol seconds is consistent with it:
                # shrink the residual by the model's slope times the tolerance (first order),
                # so millisecond clock and latency offsets do not read as divergence
                slack = abs(_slope(pp, fs, i)) * pp[P_TOL]
                r = r - slack if r > slack else (r + slack if r < -slack else 0.0)
            nev = _residual(pp, fs, ch, buf, i, raw, r, t, ev, nev)
    fs[S_PRED + 4] = fs[S_PX]
    fs[S_PRED + 5] = fs[S_PY]
    fs[S_PRED + 6] = math.degrees(fs[S_PPHI])
    for j in range(3):
        fs[S_MEAS + 4 + j] = row[8 + j]
    if not (math.isnan(row[8]) or math.isnan(row[9]) or math.isnan(row[10])):
        nev = _pose_residuals(row, pp, fs, ch, buf, ev, nev)
    for e in range(nev):
        c = int(ev[e, E_CH])
        ev[e, E_PRED] = fs[S_PRED + c]
        ev[e, E_MEAS] = fs[S_MEAS + c]
    return nev


@njit(cache=True)
def monitor_run(rows, start, pp, fs, ch, buf, queue, qi, ev, tab, q):
    """Run :func:`monitor_step` over ``rows[start:]``; stop after the first row with events.

    Returns ``(next_row, n_events)``; ``next_row == len(rows)`` when all rows are done. The
    replay uses this to handle events in Python exactly as a live monitor would, sample by sample.
    """
    n = rows.shape[0]
    for r in range(start, n):
        if qi[1] >= queue.shape[0]:
            return r, -1  # the caller grows the command queue and resumes at this row
        nev = monitor_step(rows[r], pp, fs, ch, buf, queue, qi, ev, tab, q)
        if nev > 0:
            return r + 1, nev
    return n, 0
