"""Step 1, localise: the model on every recording, where and how it misses the data."""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ...io.recording import Recording
from ...model.calibration import Calibration
from ...model.kinematics import command_to_wheels
from ...model.robot import RobotProfile
from ...model.simulate import simulate_batch, steady_state
from ...prediction import (
    controller_clock_s,
    first_moving_row,
    initial_wheel_rpm,
    start_pose,
    with_tick_phase,
    without_frozen_start,
)
from ..fit import (
    few_threads,
    pose_scale,
)
from ..regimes import noise_sd, rmse

STRUCTURE_RATIO = 1.2
#: ... with a lag-1 autocorrelation above this.
STRUCTURE_RHO = 0.2


# --------------------------------------------------------------------------- evaluation


def initial_pose_at_rest(rec: Recording) -> Recording:
    """The recording with its first pose replaced by the mean pose over the initial rest.

    The model starts from the first pose; a camera's noise on it would rotate the whole
    predicted path (0.3 deg of heading noise is 10 cm after 20 m), so it is averaged over the
    samples before the first command that moves the robot (headings as a circular mean) and
    put in the first row. That row may be a command row without a pose of its own: it then
    gains one pose sample (the robot is at rest there, so it is a true one).
    """
    pose = rec.pose
    if len(rec) < 3:
        return rec
    # the sample at which the first moving command takes effect is still at rest
    rest = pose[:first_moving_row(rec) + 1]
    rest = rest[np.isfinite(rest).all(axis=1)]
    if len(rest) < 2:
        return rec
    ph = np.deg2rad(rest[:, 2])
    first = np.array([rest[:, 0].mean(), rest[:, 1].mean(),
                      np.rad2deg(np.arctan2(np.sin(ph).mean(), np.cos(ph).mean()))])
    new = pose.copy()
    new[0] = first
    return rec.with_values(pose=new)



class _Evaluator:
    """The model on every recording, many calibrations per call (pure, batched).

    Recordings sampled on the same uniform grid are padded to the longest (the last command
    held) and simulated as one batch; others one by one.
    """

    def __init__(self, recordings: Sequence[Recording], robot: RobotProfile):
        # where a recording starts in motion the model starts in steady state at the measured
        # speeds; frozen leading readings are neither motion nor data
        self.start_rpm = [initial_wheel_rpm(r) for r in recordings]
        self.recs = [without_frozen_start(r) for r in recordings]
        self.clock_s = [controller_clock_s(r) for r in recordings]
        self.start_target = [command_to_wheels(r.commands[:1, 0], r.commands[:1, 1],
                                               r.commands[:1, 2], robot.k)[0]
                             for r in self.recs]
        self.robot = robot
        self.pose0 = np.array([start_pose(r) for r in self.recs], dtype=float)
        self.pose_scale = [pose_scale(r.t_s[-1] - r.t_s[0], robot) for r in self.recs]
        #: pose noise per recording and channel (in pose_scale units), see :meth:`set_pose_noise`
        self.pose_sd = np.ones((len(self.recs), 3))
        self.groups: list[tuple[list[int], np.ndarray, np.ndarray]] = []
        by_dt: dict[float, list[int]] = {}
        for i, r in enumerate(self.recs):
            d = np.diff(r.t_s)
            dt = float(np.median(d))
            if np.allclose(d, dt, rtol=1e-6, atol=1e-9):
                by_dt.setdefault(round(dt, 12), []).append(i)
            else:
                self.groups.append(([i], r.t_s - r.t_s[0], r.commands[None].copy()))
        for dt, idx in by_dt.items():
            n = max(len(self.recs[i]) for i in idx)
            cmd = np.empty((len(idx), n, 3))
            for j, i in enumerate(idx):
                c = self.recs[i].commands
                cmd[j, :len(c)] = c
                cmd[j, len(c):] = c[-1]
            self.groups.append((idx, np.arange(n) * dt, cmd))

    def predict(self, calibs: Sequence[Calibration | Sequence[Calibration]],
                subset: Sequence[int] | None = None
                ) -> list[dict[int, tuple[np.ndarray, np.ndarray]]]:
        """Wheel speeds and poses for each calibration; an entry may instead be a sequence with
        one calibration per recording. Returns, per entry, recording -> (wheel, pose)."""
        keep = set(range(len(self.recs)) if subset is None else subset)
        out: list[dict[int, tuple[np.ndarray, np.ndarray]]] = [{} for _ in calibs]
        for idx, t, cmd in self.groups:
            sel = [j for j, i in enumerate(idx) if i in keep]
            if not sel:
                continue
            per_robot, owners = [], []
            for k, c in enumerate(calibs):
                for j in sel:
                    per_robot.append(c if isinstance(c, Calibration) else c[idx[j]])
                    owners.append((k, j))
            cmds = np.concatenate([cmd[sel]] * len(calibs))
            pose0 = np.concatenate([self.pose0[[idx[j] for j in sel]]] * len(calibs))
            state = cmd0 = None
            moving = any(self.start_rpm[idx[j]].any() for j in sel)
            phased = any(c.effects.controller_period_s > 0 for c in per_robot) and any(
                self.clock_s[idx[j]] is not None for j in sel)
            if moving or phased:
                state = np.stack([with_tick_phase(
                    steady_state(c, self.start_rpm[idx[j]], self.start_target[idx[j]]),
                    c, self.clock_s[idx[j]])
                    for c, (_, j) in zip(per_robot, owners, strict=True)])
            if moving:
                # a recording at rest keeps the default: nothing in force before its start
                cmd0 = np.stack([cmds[row, 0] if self.start_rpm[idx[j]].any() else
                                 np.zeros(3) for row, (_, j) in enumerate(owners)])
            with few_threads(cmds.size):
                traj = simulate_batch(cmds, t, per_robot, self.robot, initial_pose=pose0,
                                      initial_state=state, initial_command=cmd0)
            for row, (k, j) in enumerate(owners):
                n = len(self.recs[idx[j]])
                out[k][idx[j]] = (traj.wheel_rpm[row, :n], traj.pose[row, :n])
        return out

    def wheel_residuals(self, pred: Mapping[int, tuple[np.ndarray, np.ndarray]]
                        ) -> dict[int, np.ndarray]:
        """Measured minus model wheel speeds (T, 4) [rpm], NaN where not measured."""
        return {i: self.recs[i].wheel_rpm - w for i, (w, _) in pred.items()}

    def pose_residuals(self, pred: Mapping[int, tuple[np.ndarray, np.ndarray]]
                       ) -> dict[int, np.ndarray]:
        """Measured minus model pose (T, 3) in wheel-rpm equivalents, NaN where not measured."""
        out = {}
        for i, (_, p) in pred.items():
            d = self.recs[i].pose - p
            d[:, 2] = (d[:, 2] + 180.0) % 360.0 - 180.0
            out[i] = d * self.pose_scale[i]
        return out

    def set_pose_noise(self, cal: Calibration) -> bool:
        """Estimate the pose noise of each recording and channel from the residual of ``cal``;
        False when no recording has a usable pose."""
        res = self.pose_residuals(self.predict([cal])[0])
        sd = np.array([[noise_sd(res[i][:, c]) for c in range(3)] for i in range(len(res))])
        self.pose_sd = np.where(np.isfinite(sd) & (sd > 0), sd, np.nan)
        return bool(np.isfinite(self.pose_sd).any())

    def channel(self, pred, channel: str) -> dict[int, np.ndarray]:
        """Finite residuals per recording, flattened: ``"wheel"`` in [rpm]; ``"pose"`` divided
        by each recording's and channel's noise level (a channel without one is left out)."""
        if channel == "wheel":
            res = self.wheel_residuals(pred)
        else:
            res = {i: r / self.pose_sd[i] for i, r in self.pose_residuals(pred).items()}
        return {i: r[np.isfinite(r)] for i, r in res.items()}

    def has_pose(self) -> bool:
        return any(np.isfinite(r.pose).any() for r in self.recs)



# --------------------------------------------------------------------------- results


@dataclass(frozen=True)
class ResidualCheck:
    """Is what remains noise?

    Attributes
    ----------
    rmse_rpm, noise_rpm : float
        Remaining wheel RMSE and the noise level [rpm].
    ratio : float
        ``rmse_rpm / noise_rpm`` [-].
    lag1_autocorrelation : float
        Of the remaining wheel residual, pooled over recordings and wheels [-].
    structured : bool
        ``ratio > STRUCTURE_RATIO`` and autocorrelation above ``STRUCTURE_RHO``.
    """

    rmse_rpm: float
    noise_rpm: float
    ratio: float
    lag1_autocorrelation: float
    structured: bool


def lag1_autocorrelation(residuals: Sequence[np.ndarray]) -> float:
    """Pooled lag-1 autocorrelation of residual arrays (T, k), within recordings and columns,
    between each column's consecutive measured samples (rows without a measurement, a
    recorded run's command rows, are skipped: counted as breaks they diluted it)."""
    num = den = 0.0
    for r in residuals:
        r2 = np.asarray(r, float).reshape(len(r), -1)
        for c in range(r2.shape[1]):
            v = r2[np.isfinite(r2[:, c]), c]
            num += float(v[:-1] @ v[1:])
            den += float(v @ v)
    return num / den if den > 0 else 0.0


def residual_check(residuals: Sequence[np.ndarray], noise_rpm: float) -> ResidualCheck:
    """:class:`ResidualCheck` of wheel residual arrays (T, 4)."""
    e = rmse(np.concatenate([np.asarray(r).ravel() for r in residuals]))
    ratio = e / noise_rpm if noise_rpm > 0 else math.inf
    rho = lag1_autocorrelation(residuals)
    return ResidualCheck(e, noise_rpm, ratio, rho,
                         bool(ratio > STRUCTURE_RATIO and rho > STRUCTURE_RHO))



def _rmse_per_recording(ev: _Evaluator, cal: Calibration
                        ) -> tuple[float, tuple[float, ...], tuple[float, ...], list[np.ndarray]]:
    """Wheel RMSE overall and per recording [rpm], pose RMSE (X [m], Y [m], phi [deg]) and the
    wheel residual arrays."""
    pred = ev.predict([cal])[0]
    res = ev.wheel_residuals(pred)
    wheel = [res[i] for i in range(len(ev.recs))]
    pose = [ev.recs[i].pose - pred[i][1] for i in range(len(ev.recs))]
    for p in pose:
        p[:, 2] = (p[:, 2] + 180.0) % 360.0 - 180.0
    allp = np.concatenate(pose)
    return (rmse(np.concatenate([r.ravel() for r in wheel])),
            tuple(rmse(r) for r in wheel), tuple(rmse(allp[:, c]) for c in range(3)), wheel)


def _predictions(ev: _Evaluator, cal: Calibration) -> list[Recording]:
    pred = ev.predict([cal])[0]
    return [r.with_values(wheel_rpm=pred[i][0], pose=pred[i][1], extra={})
            for i, r in enumerate(ev.recs)]



@dataclass(frozen=True)
class ResidualShape:
    """Where in time the remaining wheel residual sits, and whether it rings.

    Attributes
    ----------
    shares : dict of str to float
        Share of the residual's energy (sum of squares) in each phase after the target steps:
        ``onset`` (from a step to the measured crossing of half of it), ``overshoot`` (the next
        three such rise times), ``settling`` (up to 1 s after the step) and ``steady`` (the
        rest) [-].
    dominant_hz : float
        Frequency of the largest peak of the residual's spectrum [Hz] (NaN when none stands
        out: below four times the spectrum's median).
    damping : float
        Damping ratio of that peak from its half-power width ``df / (2 f)`` [-] (NaN without).
    """

    shares: dict[str, float]
    dominant_hz: float
    damping: float

    def to_json(self) -> dict[str, Any]:
        def num(v: float):
            return float(v) if math.isfinite(v) else None

        return {"shares": {k: num(v) for k, v in self.shares.items()},
                "dominant_hz": num(self.dominant_hz), "damping": num(self.damping)}

    def describe(self) -> str:
        where = max(self.shares, key=lambda k: self.shares[k]) if self.shares else "nowhere"
        text = (f"largest in the {where} phase ("
                + ", ".join(f"{k} {100 * v:.0f} %" for k, v in self.shares.items()) + ")")
        if math.isfinite(self.dominant_hz):
            text += f"; rings at {self.dominant_hz:.3g} Hz"
            if math.isfinite(self.damping):
                text += f" with damping ratio about {self.damping:.2g}"
        return text


#: A uniform grid laid over samples (the reference model's, the residual's spectrum) may hold
#: at most this many points per measured sample: more means pauses of minutes between samples.
MAX_GRID_PER_SAMPLE = 20


def residual_shape(recordings: Sequence[Recording], residuals: Sequence[np.ndarray],
                   robot: RobotProfile) -> ResidualShape:
    """:class:`ResidualShape` of wheel residual arrays (T, 4), one per recording."""
    energy = {"onset": 0.0, "overshoot": 0.0, "settling": 0.0, "steady": 0.0}
    spectra, freqs = [], None
    for rec, res in zip(recordings, residuals, strict=True):
        tg = command_to_wheels(rec.commands[:, 0], rec.commands[:, 1], rec.commands[:, 2],
                               robot.k)
        t = rec.t_s
        phase = np.full((len(rec), 4), "steady", dtype=object)
        period = rec.measured_period_s
        for w in range(4):
            y = rec.wheel_rpm[:, w]
            if not np.isfinite(y).any():
                continue
            big = 0.1 * max(float(np.nanmax(np.abs(tg[:, w]))), 1e-9)
            jumps = list(np.flatnonzero(np.abs(np.diff(tg[:, w])) > big) + 1)
            if abs(tg[0, w]) > big and not (np.abs(y[:3]) > 0.5 * abs(tg[0, w])).any():
                jumps.insert(0, 0)
            for j in jumps:
                before = tg[j - 1, w] if j else 0.0
                half = 0.5 * (before + tg[j, w])
                sgn = np.sign(tg[j, w] - before)
                after = np.flatnonzero((np.arange(len(rec)) >= j) & (sgn * (y - half) >= 0))
                t50 = t[after[0]] if after.size else t[j] + 0.1
                rise = max(t50 - t[j], period)
                dt = t - t[j]
                sel = dt >= 0
                phase[sel & (dt < 1.0), w] = "settling"
                phase[sel & (t >= t50) & (t < t50 + 3 * rise), w] = "overshoot"
                phase[sel & (t < t50), w] = "onset"
        ok = np.isfinite(res)
        for k in energy:
            m = ok & (phase == k)
            energy[k] += float(np.sum(res[m] ** 2))
        # spectrum of the wheel-mean residual on a uniform grid
        cnt = ok.sum(axis=1)
        rr = np.where(cnt > 0, np.where(ok, res, 0.0).sum(axis=1) / np.maximum(cnt, 1), np.nan)
        good = np.isfinite(rr)
        if good.sum() < 32:
            continue
        dt = float(np.median(np.diff(t[good])))
        if not dt > 0 or (t[good][-1] - t[good][0]) / dt > MAX_GRID_PER_SAMPLE * good.sum():
            continue  # long pauses between samples: no spectrum on a grid mostly empty
        tu = np.arange(t[good][0], t[good][-1], dt)
        ru = np.interp(tu, t[good], rr[good])
        ru = ru - ru.mean()
        n = 1 << math.ceil(math.log2(max(ru.size, 64))) + 1
        p = np.abs(np.fft.rfft(ru * np.hanning(ru.size), n)) ** 2
        f = np.fft.rfftfreq(n, dt)
        spectra.append(np.interp(freqs, f, p) if freqs is not None else p)
        if freqs is None:
            freqs = f
    total = sum(energy.values())
    shares = {k: (v / total if total > 0 else math.nan) for k, v in energy.items()}
    fdom = zeta = math.nan
    if spectra:
        p = np.sum(spectra, axis=0)
        lo = max(1, int(np.searchsorted(freqs, 0.5)))
        k = lo + int(np.argmax(p[lo:]))
        if p[k] > 4.0 * np.median(p[lo:]):
            fdom = float(freqs[k])
            halfp = p[k] / 2.0
            a = k
            while a > 0 and p[a] > halfp:
                a -= 1
            b = k
            while b < p.size - 1 and p[b] > halfp:
                b += 1
            zeta = float((freqs[b] - freqs[a]) / (2.0 * fdom))
    return ResidualShape(shares, fdom, zeta)


# --------------------------------------------------------------------------- findings

#: A loop lacks integral action when its proportional part leaves more than this share of the
#: target ...
P_ONLY_GAP = 0.03
#: ... and its integral closes less than this share of that gap within a typical step ...
P_ONLY_INTEGRAL = 0.1
#: ... while its proportional part settles within it (the fast pole's time constants per step).
P_ONLY_SETTLED = 5.0


@dataclass(frozen=True)
class Finding:
    """A named property of the fitted model that is not an effect of the signal path.

    Attributes
    ----------
    effect : str
        Its name (``proportional_only``).
    parameters : dict of str to float
        Its figures, with units in the names.
    description : str
        One sentence for the report.
    """

    effect: str
    parameters: dict[str, float]
    description: str


#: A wheel gain at least this far below one is checked for a level that still creeps [-].
CREEP_GAIN_GAP = 0.02
#: A creep is named when its pooled slope is this many standard errors from zero ...
CREEP_Z = 4.0
#: ... and it moves the level by this share of the target over the second half of a step [-].
CREEP_SHARE = 0.01
#: Steps shorter than this many samples are not read for a creep.
CREEP_MIN_SAMPLES = 20


def step_halves(recordings: Sequence[Recording], robot: RobotProfile, wheel: int,
                min_target_rpm: float = 10.0) -> Iterator[tuple[float, np.ndarray, np.ndarray]]:
    """The second half of every step of ``wheel``'s target of at least ``min_target_rpm``
    (:func:`mecanum_hil.identify.steps.split_steps`): its target [rpm], and the times [s] and
    measured speeds [rpm] of its finite samples (a step without one is left out)."""
    from ..regimes import wheel_targets
    from ..steps import split_steps

    for rec in recordings:
        for s in split_steps(rec.t_s, wheel_targets(rec, robot), [wheel]):
            half = slice((s.start + s.stop) // 2, s.stop)
            y = rec.wheel_rpm[half, wheel]
            ok = np.isfinite(y)
            if abs(s.target_rpm) >= min_target_rpm and ok.any():
                yield s.target_rpm, rec.t_s[half][ok], y[ok]


def _creep(recordings: Sequence[Recording], robot: RobotProfile, wheel: int
           ) -> tuple[float, float, float]:
    """Pooled slope of ``wheel``'s measured speed over the second half of its steps, towards
    each step's target [rpm/s], its standard error [rpm/s] and the mean share of the target it
    moves the level by over that half [-]; NaN without a step of at least 10 rpm."""
    num = den = var = share = 0.0
    n_steps = 0
    for target, t, y in step_halves(recordings, robot, wheel):
        if t.size < CREEP_MIN_SAMPLES // 2:
            continue
        t = t - t.mean()
        slope, icpt = np.polyfit(t, y, 1)
        towards = 1.0 if target >= icpt else -1.0
        sxx = float(t @ t)
        resid = y - (slope * t + icpt)
        num += towards * slope * sxx
        den += sxx
        var += float(resid @ resid) / max(t.size - 2, 1) * sxx
        share += towards * slope * float(np.ptp(t)) / abs(target)
        n_steps += 1
    if not n_steps or den <= 0:
        return math.nan, math.nan, math.nan
    return num / den, math.sqrt(var) / den, share / n_steps


def creeping_levels(calibration: Calibration, recordings: Sequence[Recording],
                    robot: RobotProfile, wheels: Sequence[int]) -> list[Finding]:
    """Wheels given a gain below one whose measured level still creeps towards the target.

    A gain below one says the loop settles short of its target for good. Where the measured
    speed still moves towards the target at the end of the steps (:data:`CREEP_Z` standard
    errors, :data:`CREEP_SHARE` of the target over their second half), the gain is the level
    the steps reached, not one the loop settles at: a slow integral, a drift of the motor or a
    coarsely quantised drive output do that, and the model, holding the level flat, does not.
    Nothing is added to the calibration.
    """
    out = []
    for w in wheels:
        gain = calibration.effects.gains[w]
        if gain > 1.0 - CREEP_GAIN_GAP:
            continue
        slope, se, share = _creep(recordings, robot, w)
        if not (slope > CREEP_Z * se and share >= CREEP_SHARE):
            continue
        out.append(Finding(
            "creeping_level", {"wheel": float(w + 1), "creep_rpm_per_s": slope, "gain": gain},
            f"wheel {w + 1}'s level still creeps towards its target at {slope:.3g} rpm/s "
            f"({100 * share:.1f} % of it over the second half of its steps): its gain of "
            f"{gain:.3f} is the level the steps reached, not one the loop settles at; a slow "
            f"integral, a drifting motor or a coarsely quantised output would creep so"))
    return out


def typical_step_s(recordings: Sequence[Recording], robot: RobotProfile) -> float:
    """Median duration of the steps of the wheel targets over all recordings [s] (NaN without
    steps); see :mod:`mecanum_hil.identify.steps`."""
    from ..regimes import wheel_targets
    from ..steps import split_steps

    durations = []
    for rec in recordings:
        wheels = [w for w in range(4) if np.isfinite(rec.wheel_rpm[:, w]).any()]
        for s in split_steps(rec.t_s, wheel_targets(rec, robot), wheels):
            end = rec.t_s[s.stop] if s.stop < len(rec) else rec.t_s[-1]
            durations.append(float(end - s.t_start_s))
    return float(np.median(durations)) if durations else math.nan


def proportional_only(calibration: Calibration, step_s: float,
                      wheels: Sequence[int] = (0, 1, 2, 3)) -> Finding | None:
    """The missing integral action, when the model shows it: a proportional-only speed loop.

    With ``A`` the loop's proportional and ``C`` its integral gain (times the motor's), the
    proportional part alone settles at ``A / (A + B)`` of the target with the time constant
    ``1 / (A + B)``, and the integral then closes the rest with the slow time constant about
    ``(A + B) / C``. Named when, over a typical step of ``step_s``, the proportional part
    settles (``(A + B) step_s >= P_ONLY_SETTLED``), the integral closes less than
    ``P_ONLY_INTEGRAL`` of the gap (``C step_s / (A + B)`` below it), and the level, with the
    model's ``wheel_gain`` of the measured ``wheels`` [0-based] (their median), sits more than
    ``P_ONLY_GAP`` below the target: every level then sits at a fixed fraction of its target.
    A loop whose gains bring the level back to the target (a slow mode of a PI loop that the
    coefficients settled on, the gains making up the level) is not named. The model already
    reproduces it (``C`` near 0): nothing is added to the calibration.
    """
    A, B, C = calibration.A, calibration.B, calibration.C
    if not (math.isfinite(step_s) and step_s > 0 and A + B > 0):
        return None
    gain = float(np.median([calibration.effects.gains[w] for w in wheels])) if wheels else 1.0
    ratio = gain * A / (A + B)
    if (A + B) * step_s < P_ONLY_SETTLED or 1.0 - ratio <= P_ONLY_GAP \
            or C * step_s / (A + B) >= P_ONLY_INTEGRAL:
        return None
    slow = (A + B) / C if C > 0 else math.inf
    return Finding("proportional_only",
                   {"level_ratio": ratio, "integral_time_s": slow},
                   f"no integral action: every level settles at {100 * ratio:.1f} % of its "
                   f"target (A / (A + B), times the wheels' gain); the integral would take "
                   f"about {slow:.3g} s to close the rest, far longer than a step (C near 0)")
