"""Diagnose: find where model and robot disagree, name the missing physical effect, add it, refit.

The method (``docs/diagnose.md`` has the details and the reasons):

1. **Localise.** The residual (measured minus model) of the calibration as given is broken down
   by recording, wheel and pose channel, and regime (:mod:`mecanum_hil.identify.regimes`). The
   wheel noise level ``sigma`` is estimated without a model from the residual's differences.
2. **Baseline.** A, B, C (and the parameters of effects already in the calibration) are refitted
   on the data, so no candidate gets credit for a mere refit.
3. **Rounds.** Every effect of the library not yet in the model (:data:`CANDIDATES`) is fitted
   *together with* A, B, C and the effects already accepted, by the least-squares engine
   :func:`mecanum_hil.identify.fit.fit_parameters` (the deadband, whose effect on the data is
   piecewise constant in its parameter, by a 1-D grid with the rest refitted by least squares).
   Each fitted model, and the baseline, is scored on **held-out** data: approximate
   leave-one-recording-out, i.e. for each recording one Gauss-Newton step from the full fit
   using all *other* recordings, then the left-out recording simulated exactly with those
   parameters. The held-out mean square wheel residual, divided by ``sigma^2``, is the score;
   extra parameters are paid for by the held-out evaluation itself (a parameter that only fits
   noise makes the held-out score worse) plus two minimum improvements: the best candidate is
   added only if it removes at least :data:`MIN_EXPLAINED` of the held-out *excess* over the
   noise floor (and of the in-sample excess too: the approximate held-out score of a
   misspecified model is itself noisy) and at least :data:`MIN_RELATIVE` of the held-out
   score. Rounds repeat until none qualifies or the residual is at the noise floor.
4. **Slip** changes no wheel speed, only the pose: after the wheel rounds, when recordings
   have pose data, its efficiencies are fitted on the pose channels (A, B, C held at their
   wheel fit, which pins them) and scored the same way on the pose residuals, each recording's
   channel divided by its own noise level.
5. **Unexplained.** If the remaining wheel residual is still above the noise
   (``rmse > STRUCTURE_RATIO * sigma``) and structured (lag-1 autocorrelation above
   :data:`STRUCTURE_RHO`; white noise has about 0), no effect of the library explains it and
   the diagnosis says ``unexplained``. A step accepted on the way that explained less than
   :data:`CONFIRM_EXPLAINED` of its round's gap is then withdrawn (with the steps after it):
   a missing effect of the library, fitted with the right physics, removes nearly all of its
   share, while the closest wrong effect standing in for an unknown one removes only part.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..errors import ConfigError, DiagnoseError, FitError
from ..io.recording import Recording
from ..model.calibration import EFFECTS, Calibration
from ..model.kinematics import command_to_wheels
from ..model.robot import RobotProfile
from ..model.simulate import simulate_batch
from ..prediction import first_moving_row, require_commands, start_pose
from .fit import (
    DEFAULT_BOUNDS,
    FitResult,
    few_threads,
    fit_parameters,
    parameter_value,
    pose_scale,
    toml_key,
    with_parameters,
)
from .regimes import Localisation, localise, noise_sd, pooled_noise_sd, rmse

#: Candidate effects, in the order they are tried (the names of :data:`EFFECTS`).
CANDIDATES: tuple[str, ...] = ("dead_time", "saturation", "rate_limit", "deadband", "wheel_gain",
                               "slip")

#: A candidate must remove at least this fraction of the held-out excess over the noise floor.
MIN_EXPLAINED = 0.5
#: ... and at least this fraction of the held-out score itself.
MIN_RELATIVE = 0.05
#: When structured residual remains at the end, a step is kept only if it explained this much.
CONFIRM_EXPLAINED = 0.75
#: Smallest in-sample excess over the noise floor, as a share of the in-sample score, for which
#: a candidate's in-sample share is computed (below it there is nothing to explain: 0).
MIN_EXCESS = 0.02
#: Held-out score (mean square / sigma^2) at or below which nothing significant is left.
NOISE_FLOOR_SCORE = 1.1
#: Remaining residual is "structured" above this RMSE / noise ratio ...
STRUCTURE_RATIO = 1.2
#: ... with a lag-1 autocorrelation above this.
STRUCTURE_RHO = 0.2

_COEFFICIENTS = ("A", "B", "C")
# finite-difference steps of the held-out Jacobian: relative, with a floor in the unit
_FD_RELATIVE = 1e-4
_LOO_RCOND = 1e-4
_FD_FLOOR = {"A": 1e-3, "B": 1e-3, "C": 1e-2, "dead_time_s": 1e-4, "top_speed_rpm": 1e-2,
             "rate_limit_rpm_per_s": 1e-1, "deadband_rpm": 1e-2}


def effect_parameters(effect: str) -> tuple[str, ...]:
    """The engine's parameter names (:data:`~mecanum_hil.identify.fit.PARAMETER_NAMES`) of an
    effect: ``gains`` -> ``gains[0]`` .. ``gains[3]``, ``efficiency`` -> three."""
    out: list[str] = []
    for p in EFFECTS[effect].parameters:
        if p == "gains":
            out += [f"gains[{i}]" for i in range(4)]
        elif p == "efficiency":
            out += [f"efficiency[{i}]" for i in range(3)]
        else:
            out.append(p)
    return tuple(out)


def _effect_values(cal: Calibration, effect: str) -> dict[str, Any]:
    """An effect's parameters as in :class:`Effects` (lists for gains and efficiency)."""
    out = {}
    for p in EFFECTS[effect].parameters:
        v = getattr(cal.effects, p)
        out[p] = [float(x) for x in v] if isinstance(v, tuple) else float(v)
    return out


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
        self.recs = list(recordings)
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
            with few_threads(cmds.size):
                traj = simulate_batch(cmds, t, per_robot, self.robot, initial_pose=pose0)
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


@dataclass(frozen=True)
class HeldOut:
    """In-sample and held-out fit of one model on one channel group.

    Attributes
    ----------
    fit_ms, heldout_ms : float
        Mean square residual over all samples, in sample and held out [channel unit^2].
    heldout_ms_per_recording : tuple of float
    """

    fit_ms: float
    heldout_ms: float
    heldout_ms_per_recording: tuple[float, ...]


def _steps(x: np.ndarray, free: Sequence[str]) -> np.ndarray:
    floor = np.array([_FD_FLOOR.get(n, 1e-4) for n in free])
    h = np.maximum(_FD_RELATIVE * np.abs(x), floor)
    upper = np.array([DEFAULT_BOUNDS[n][1] for n in free])
    return np.where(x + h > upper, -h, h)


def heldout_score(ev: _Evaluator, cal: Calibration, free: Sequence[str],
                  channel: str = "wheel") -> HeldOut:
    """Approximate leave-one-recording-out residual of a fitted model (module docstring, 3.).

    Parameters
    ----------
    ev : _Evaluator
        The recordings.
    cal : Calibration
        The model fitted on all recordings.
    free : sequence of str
        Its fitted parameters, moved for each left-out recording (others stay fixed).
    channel : {"wheel", "pose"}
        Which residuals score the model.
    """
    base = ev.channel(ev.predict([cal])[0], channel)
    recs = [i for i in sorted(base) if base[i].size]
    n_all = sum(base[i].size for i in recs)
    if n_all == 0:
        raise DiagnoseError(f"no measured {channel} samples to score the model on")
    fit_ms = sum(float(base[i] @ base[i]) for i in recs) / n_all
    free = list(free)
    if not free or len(recs) < 2:
        per = tuple(float(base[i] @ base[i]) / base[i].size for i in recs)
        return HeldOut(fit_ms, fit_ms, per)
    x = np.array([parameter_value(cal, n) for n in free])
    h = _steps(x, free)
    perturbed = [with_parameters(cal, {n: x[j] + (h[j] if k == j else 0.0)
                                       for j, n in enumerate(free)}) for k in range(len(free))]
    cols = [ev.channel(p, channel) for p in ev.predict(perturbed)]
    J = {i: np.stack([(base[i] - cols[k][i]) / -h[k] for k in range(len(free))], axis=1)
         for i in recs}
    lo = np.array([DEFAULT_BOUNDS[n][0] for n in free])
    hi = np.array([DEFAULT_BOUNDS[n][1] for n in free])
    left_out: list[Calibration] = []
    for i in recs:
        A = np.concatenate([J[k] for k in recs if k != i])
        b = np.concatenate([base[k] for k in recs if k != i])
        norms = np.linalg.norm(A, axis=0)
        norms[norms == 0] = 1.0
        # the one-step approximation holds for small moves only: directions the other
        # recordings barely determine are cut off (rcond), and each move is capped at half the
        # parameter's size, so a recording that alone pins a parameter cannot fling it away
        step = -np.linalg.lstsq(A / norms, b, rcond=_LOO_RCOND)[0] / norms
        cap = 0.5 * np.maximum(np.abs(x), 100.0 * h)
        xi = np.clip(x + np.clip(step, -cap, cap), lo, hi)
        try:
            left_out.append(with_parameters(cal, dict(zip(free, xi, strict=True))))
        except ConfigError:  # the step left the stable region: keep the full fit
            left_out.append(cal)
    per_rec = {i: c for i, c in zip(recs, left_out, strict=True)}
    batch = [per_rec.get(i, cal) for i in range(len(ev.recs))]
    held = ev.channel(ev.predict([batch], subset=recs)[0], channel)
    per = tuple(float(held[i] @ held[i]) / held[i].size for i in recs)
    heldout_ms = sum(float(held[i] @ held[i]) for i in recs) / n_all
    return HeldOut(fit_ms, heldout_ms, per)


# --------------------------------------------------------------------------- candidates


def _smoothed(w: np.ndarray) -> np.ndarray:
    k = np.ones(3) / 3.0
    out = np.stack([np.convolve(np.nan_to_num(w[:, i]), k, "same") for i in range(w.shape[1])], 1)
    out[~np.isfinite(w)] = np.nan
    out[[0, -1]] = np.nan  # the convolution's edges see padding
    return out


def _latency_s(ev: _Evaluator, noise_rpm: float) -> float:
    """Model-free dead time guess: median delay from a large jump of a wheel target to the
    first measured departure of that wheel by more than four noise levels, less one sample."""
    lat, dts = [], []
    for r in ev.recs:
        tg = command_to_wheels(r.commands[:, 0], r.commands[:, 1], r.commands[:, 2], ev.robot.k)
        w, t = r.wheel_rpm, r.t_s
        dts.append(float(np.median(np.diff(t))))
        big = max(20.0 * noise_rpm, 5.0)
        for i in range(4):
            if not np.isfinite(w[:, i]).any():
                continue
            for j in np.flatnonzero(np.abs(np.diff(tg[:, i])) >= big) + 1:
                if j < 3 or not np.all(tg[j - 3:j, i] == tg[j - 1, i]):
                    continue
                w0 = np.nanmean(w[j - 2:j + 1, i])
                sgn = np.sign(tg[j, i] - tg[j - 1, i])
                window = (t > t[j]) & (t <= t[j] + 1.0)
                hit = np.flatnonzero(window & (sgn * (w[:, i] - w0) > 4.0 * noise_rpm))
                if hit.size:
                    lat.append(t[hit[0]] - t[j])
    if not lat:
        return 0.0
    # whole microseconds: differences of sample times carry rounding noise
    return round(max(float(np.median(lat)) - float(np.median(dts)), 0.0), 6)


def _start_values(effect: str, ev: _Evaluator, noise_rpm: float) -> dict[str, float]:
    """Data-driven starting values of an effect's parameters (engine names).

    They matter: the coefficients of a fit without the effect have absorbed part of it (a slow
    model mimics a dead time or a ramp), so starting the effect at "absent" leaves the search in
    that local optimum. Each start is read off the measurements without the model.
    """
    recs = ev.recs
    if effect == "dead_time":
        return {"dead_time_s": _latency_s(ev, noise_rpm)}
    if effect == "rate_limit":
        # a ramp limit caps the measured acceleration: start at the steepest one
        best = 1.0
        for r in recs:
            d = np.abs(np.diff(_smoothed(r.wheel_rpm), axis=0)) / np.diff(r.t_s)[:, None]
            d = d[np.isfinite(d)]
            if d.size:
                best = max(best, float(d.max()))
        return {"rate_limit_rpm_per_s": best}
    if effect == "saturation":
        peak = max(float(np.nanmax(np.abs(_smoothed(r.wheel_rpm)))) for r in recs)
        return {"top_speed_rpm": 1.02 * peak}
    if effect == "wheel_gain":
        # steady-state ratio of measured speed to target, per wheel
        num, den = np.zeros(4), np.zeros(4)
        for r in recs:
            tg = command_to_wheels(r.commands[:, 0], r.commands[:, 1], r.commands[:, 2],
                                   ev.robot.k)
            ok = (np.abs(tg) > 10.0) & np.isfinite(r.wheel_rpm)
            ok[1:] &= np.abs(np.diff(tg, axis=0)) < 1e-9
            num += np.where(ok, r.wheel_rpm * tg, 0.0).sum(axis=0)
            den += np.where(ok, tg * tg, 0.0).sum(axis=0)
        g = np.where(den > 0, num / np.where(den > 0, den, 1.0), 1.0)
        return {f"gains[{i}]": float(np.clip(g[i], 0.2, 3.0)) for i in range(4)}
    if effect == "slip":
        return {f"efficiency[{i}]": 1.0 for i in range(3)}
    return {}


def _candidate_bounds(effect: str, guess: Mapping[str, float]) -> dict[str, tuple[float, float]]:
    """Finite search ranges: an effect that is absent drives its parameter towards "absent"
    (an infinite ceiling or ramp limit), which a bounded search reaches in a few steps instead
    of chasing it through hundreds of evaluations."""
    if effect == "dead_time":
        return {"dead_time_s": (0.0, 0.5)}
    if effect == "saturation":
        g = guess["top_speed_rpm"]
        return {"top_speed_rpm": (0.2 * g, 3.0 * g)}
    if effect == "rate_limit":
        g = guess["rate_limit_rpm_per_s"]
        return {"rate_limit_rpm_per_s": (min(1.0, 0.05 * g), 20.0 * g)}
    if effect == "wheel_gain":
        return {f"gains[{i}]": (0.1, 3.0) for i in range(4)}
    if effect == "slip":
        return {f"efficiency[{i}]": (0.05, 2.0) for i in range(3)}
    return {}


@dataclass(frozen=True)
class CandidateScore:
    """One candidate of one round.

    Attributes
    ----------
    effect : str
    parameters : dict
        Its fitted parameters (as in :class:`~mecanum_hil.model.Effects`).
    ci95 : dict of str to (float, float)
        95 % intervals of its parameters (engine names).
    fit_rmse, heldout_rmse : float
        In-sample and held-out RMS residual of the scored channel [rpm or rpm equivalent].
    explained : float
        Fraction of the held-out excess over the noise floor it removes [-].
    relative : float
        Fraction of the held-out score it removes [-].
    accepted : bool
    note : str
        Why it failed, when it did (fit error).
    in_sample : float
        Fraction of the in-sample excess over the noise floor it removes [-].
    """

    effect: str
    parameters: dict[str, Any]
    ci95: dict[str, tuple[float, float]]
    fit_rmse: float
    heldout_rmse: float
    explained: float
    relative: float
    accepted: bool = False
    note: str = ""
    in_sample: float = math.nan


@dataclass(frozen=True)
class _Fitted:
    effect: str
    calibration: Calibration
    free: tuple[str, ...]
    ci95: dict[str, tuple[float, float]]
    warnings: tuple[str, ...]


def _deadband_grid(ev: _Evaluator, cal: Calibration, values: np.ndarray
                   ) -> tuple[np.ndarray, int]:
    """Wheel SSE for each deadband value (A, B, C held), on the recordings it can change."""
    rob = ev.robot
    touched = []
    top = float(values.max())
    for i, r in enumerate(ev.recs):
        tg = np.abs(command_to_wheels(r.commands[:, 0], r.commands[:, 1], r.commands[:, 2],
                                      rob.k))
        if ((tg > 1e-9) & (tg < top)).any():
            touched.append(i)
    if not touched:
        return np.zeros(values.size), 0
    cals = [with_parameters(cal, {"deadband_rpm": float(v)}) for v in values]
    sse = np.empty(values.size)
    n = 0
    for k, pred in enumerate(ev.predict(cals, subset=touched)):
        res = ev.channel(pred, "wheel")
        sse[k] = sum(float(r @ r) for r in res.values())
        n = sum(r.size for r in res.values())
    return sse, n


def _fit_deadband(ev: _Evaluator, base: Calibration, base_free: Sequence[str],
                  sources: Sequence[str]) -> _Fitted:
    """Deadband by a coarse-to-fine grid (A, B, C held), then the rest by least squares, then
    the grid again; the interval is the set of grid values whose SSE is within the 95 % F-test
    bound of the best."""
    targets = np.concatenate([np.abs(command_to_wheels(
        r.commands[:, 0], r.commands[:, 1], r.commands[:, 2], ev.robot.k)).ravel()
        for r in ev.recs])
    targets = targets[targets > 1e-9]
    top = float(min(0.3 * targets.max(), 30.0)) if targets.size else 0.0
    if top <= 0.5:
        raise FitError("no small wheel targets in the data: a deadband cannot be seen")
    cal = base

    def scan(cal: Calibration, center: float | None) -> tuple[float, tuple[float, float]]:
        coarse = np.arange(0.0, top + 1e-9, 1.0) if center is None else \
            np.arange(max(center - 1.5, 0.0), center + 1.5 + 1e-9, 0.1)
        sse, n = _deadband_grid(ev, cal, coarse)
        best = float(coarse[int(np.argmin(sse))])
        if center is None:
            return scan(cal, best)
        lim = sse.min() * (1.0 + 3.84 / max(n - len(base_free) - 1, 1))
        ok = coarse[sse <= lim]
        return best, (float(ok.min()), float(ok.max()))

    db, _ = scan(cal, None)
    cal = with_parameters(cal, {"deadband_rpm": db})
    res = fit_parameters(ev.recs, cal, ev.robot, list(base_free),
                         x0={n: parameter_value(cal, n) for n in base_free}, sources=sources)
    cal = with_parameters(cal, res.parameters)
    db, ci = scan(cal, db)
    cal = with_parameters(cal, {"deadband_rpm": db})
    return _Fitted("deadband", cal, tuple(base_free), {**res.ci95, "deadband_rpm": ci},
                   res.warnings)


def degenerate(cal: Calibration) -> bool:
    """Whether the coefficients sit in a corner of the model: ``C`` (the drive's integral
    action) or ``B`` (the motor pole) at their bound. A fit without a missing effect can end
    there (e.g. ``C -> 0`` mimics a ceiling with a lower steady-state gain), and a search that
    adds the effect from there stays stuck."""
    return cal.C <= 1e-4 or cal.B <= 1e-6


def fit_candidate(ev: _Evaluator, effect: str, base: Calibration, base_free: Sequence[str],
                  sources: Sequence[str], noise_rpm: float, two_stage: bool = True) -> _Fitted:
    """Fit one candidate effect together with ``base_free`` (A, B, C and accepted effects).

    The search starts from the effect's data-driven values (:func:`_start_values`). With
    ``two_stage`` (default) A, B, C (and accepted effects) are first refitted with the effect
    held at that start, so they give back what they had absorbed; then all are fitted jointly.
    A fit without the effect can sit in a degenerate corner (:func:`degenerate`, e.g. C at its
    bound) from which neither stage leaves: then the joint search runs from the engine's coarse
    grid of A, B, C (its best local minima, the effect at its start) and from the model as it
    is, and the lowest SSE wins. Returns the fitted model; ``free`` lists the parameters fitted
    continuously (the deadband is fitted on a grid and held during the held-out evaluation).
    """
    if effect == "deadband":
        return _fit_deadband(ev, base, base_free, sources)
    new = effect_parameters(effect)
    guess = _start_values(effect, ev, noise_rpm)
    bounds = _candidate_bounds(effect, guess)
    cal = with_parameters(base, guess)
    if effect == "slip":
        # slip changes no wheel speed, and the wheel speeds are what pin A, B, C (they were
        # fitted on them); freeing them on the pose would credit slip with a coefficient
        # change, so only the efficiencies are fitted, on the pose channels
        res = fit_parameters(ev.recs, cal, ev.robot, list(new), x0=guess, bounds=bounds,
                             pose_weight=1.0, sources=sources)
        return _Fitted(effect, with_parameters(cal, res.parameters),
                       tuple(n for n in base_free if n.startswith("efficiency")) + new,
                       dict(res.ci95), res.warnings)
    free = list(base_free) + list(new)
    if degenerate(base):
        # from a corner no local search leaves (C -> 0 mimics a ceiling with a lower gain):
        # the engine's coarse grid restarts A, B, C with the effect at its start, and the
        # joint search runs from each of the grid's best minima; the search from where the
        # model is competes with them
        x0 = {n: parameter_value(cal, n) for n in free if n not in _COEFFICIENTS}
        res = _best_fit([
            lambda: fit_parameters(ev.recs, cal, ev.robot, free, x0=x0, bounds=bounds,
                                   sources=sources),
            lambda: fit_parameters(ev.recs, cal, ev.robot, free,
                                   x0={n: parameter_value(cal, n) for n in free},
                                   bounds=bounds, sources=sources)])
        return _Fitted(effect, with_parameters(cal, res.parameters), tuple(free),
                       dict(res.ci95), res.warnings)
    if two_stage:
        x0 = {n: parameter_value(cal, n) for n in base_free}
        first = fit_parameters(ev.recs, cal, ev.robot, list(base_free), x0=x0,
                               sources=sources)
        cal = with_parameters(cal, first.parameters)
    res: FitResult = fit_parameters(ev.recs, cal, ev.robot, free,
                                    x0={n: parameter_value(cal, n) for n in free},
                                    bounds=bounds, sources=sources)
    return _Fitted(effect, with_parameters(cal, res.parameters), tuple(free), dict(res.ci95),
                   res.warnings)


def _best_fit(searches: Sequence[Callable[[], FitResult]]) -> FitResult:
    """The lowest-SSE result of several searches; a search that fails is skipped (the error
    of the first is raised when all fail)."""
    best, errors = None, []
    for search in searches:
        try:
            res = search()
        except FitError as err:
            errors.append(err)
            continue
        if best is None or res.sse < best.sse:
            best = res
    if best is None:
        raise errors[0]
    return best


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
    """Pooled lag-1 autocorrelation of residual arrays (T, k), within recordings and columns."""
    num = den = 0.0
    for r in residuals:
        r2 = np.asarray(r, float).reshape(len(r), -1)
        a, b = r2[:-1], r2[1:]
        ok = np.isfinite(a) & np.isfinite(b)
        num += float(np.sum(a[ok] * b[ok]))
        fin = r2[np.isfinite(r2)]
        den += float(np.sum(fin * fin))
    return num / den if den > 0 else 0.0


def residual_check(residuals: Sequence[np.ndarray], noise_rpm: float) -> ResidualCheck:
    """:class:`ResidualCheck` of wheel residual arrays (T, 4)."""
    e = rmse(np.concatenate([np.asarray(r).ravel() for r in residuals]))
    ratio = e / noise_rpm if noise_rpm > 0 else math.inf
    rho = lag1_autocorrelation(residuals)
    return ResidualCheck(e, noise_rpm, ratio, rho,
                         bool(ratio > STRUCTURE_RATIO and rho > STRUCTURE_RHO))


@dataclass(frozen=True)
class DiagnoseStep:
    """One effect added to the model.

    Attributes
    ----------
    effect : str
    parameters : dict
        As in :class:`~mecanum_hil.model.Effects` (lists for ``gains`` and ``efficiency``).
    ci95 : dict of str to (float, float)
        95 % intervals of the effect's parameters (engine names such as ``gains[1]``).
    rmse_before, rmse_after : float
        Wheel RMSE over all samples, before and after (in sample) [rpm].
    rmse_before_per_recording, rmse_after_per_recording : tuple of float
        The same per recording [rpm].
    pose_rmse_before, pose_rmse_after : tuple of 3 float
        Pose residual RMS over all recordings: X [m], Y [m], heading [deg] (NaN without pose).
    calibration_before, calibration_after : Calibration
    candidates : tuple of CandidateScore
        Every candidate of the round.
    warnings : tuple of str
        The engine's warnings for the accepted fit.
    explained : float
        Fraction of its round's held-out excess over the noise floor it removed [-].
    """

    effect: str
    parameters: dict[str, Any]
    ci95: dict[str, tuple[float, float]]
    rmse_before: float
    rmse_after: float
    rmse_before_per_recording: tuple[float, ...]
    rmse_after_per_recording: tuple[float, ...]
    pose_rmse_before: tuple[float, ...]
    pose_rmse_after: tuple[float, ...]
    calibration_before: Calibration
    calibration_after: Calibration
    candidates: tuple[CandidateScore, ...]
    warnings: tuple[str, ...] = ()
    explained: float = math.nan


@dataclass(frozen=True)
class Diagnosis:
    """What ``diagnose`` found.

    Attributes
    ----------
    steps : tuple of DiagnoseStep
        Effects added, in order.
    unexplained : bool
        Structured residual remains that no candidate explains.
    rmse_initial, rmse_baseline, rmse_final : float
        Wheel RMSE [rpm] of the calibration as given, after refitting its own parameters, and
        of the final model.
    noise_rpm : float
        Wheel noise level [rpm].
    initial, baseline, calibration : Calibration
        The given, the refitted and the final (extended) calibration.
    localisation_initial, localisation_final : Localisation
    check : ResidualCheck
        Of the final residual.
    rejected : tuple of CandidateScore
        The candidates of the last round, none of which qualified.
    names : tuple of str
        Recording names.
    withdrawn : tuple of DiagnoseStep
        Steps taken back at the end because structured residual remained and they had
        explained less than :data:`CONFIRM_EXPLAINED` of their round's gap.
    """

    steps: tuple[DiagnoseStep, ...]
    unexplained: bool
    rmse_initial: float
    rmse_baseline: float
    rmse_final: float
    noise_rpm: float
    initial: Calibration
    baseline: Calibration
    calibration: Calibration
    localisation_initial: Localisation
    localisation_final: Localisation
    check: ResidualCheck
    rejected: tuple[CandidateScore, ...] = ()
    names: tuple[str, ...] = field(default=())
    withdrawn: tuple[DiagnoseStep, ...] = ()

    @property
    def effects(self) -> list[str]:
        """Names of the effects added."""
        return [s.effect for s in self.steps]

    def to_json(self) -> dict[str, Any]:
        """The ``--json`` document (layout fixed by issue 7)."""
        return {
            "effects": [{"effect": s.effect, "parameters": s.parameters,
                         "rmse_before": s.rmse_before, "rmse_after": s.rmse_after}
                        for s in self.steps],
            "unexplained": bool(self.unexplained),
            "rmse_initial": self.rmse_initial,
            "rmse_final": self.rmse_final,
        }


# --------------------------------------------------------------------------- the loop


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


def _score(h: HeldOut, noise2: float) -> float:
    return h.heldout_ms / noise2


def diagnose(
    recordings: Sequence[Recording],
    calibration: Calibration,
    robot: RobotProfile | None = None,
    *,
    names: Sequence[str] | None = None,
    candidates: Sequence[str] = CANDIDATES,
    max_rounds: int = 4,
    echo: Callable[[str], None] | None = None,
) -> Diagnosis:
    """Find and add the effects the model lacks (method in the module docstring).

    Parameters
    ----------
    recordings : sequence of Recording
        Commands and measured wheel speeds (pose where measured); at least two recordings, so
        that models can be compared on data they were not fitted to.
    calibration : Calibration
        The model as the user has it (e.g. written by ``fit``); effects it already has are kept
        and refitted, the others are candidates.
    robot : RobotProfile, optional
        Geometry (default: the paper's robot).
    names : sequence of str, optional
        Recording names for the report.
    candidates : sequence of str
        Effects of the library to consider (default: all of :data:`CANDIDATES`).
    max_rounds : int
        Most effects to add.
    echo : callable, optional
        Progress lines (``print``).

    Returns
    -------
    Diagnosis

    Raises
    ------
    DiagnoseError
        Fewer than two recordings, no measured wheel speeds, or an unknown candidate.
    """
    return _diagnose(recordings, calibration, robot, names, candidates, max_rounds, echo)


def _diagnose(recordings, calibration, robot, names, candidates, max_rounds, echo) -> Diagnosis:
    say = echo or (lambda _msg: None)
    rob = robot or RobotProfile()
    recs = [initial_pose_at_rest(r) for r in recordings]
    if len(recs) < 2:
        raise DiagnoseError(f"diagnose needs at least two recordings to compare models on data "
                            f"they were not fitted to; got {len(recs)}")
    for c in candidates:
        if c not in EFFECTS:
            raise DiagnoseError(f"unknown effect {c!r}; the library has {', '.join(EFFECTS)}")
    names = tuple(names) if names is not None else tuple(
        str(r.metadata.get("profile", f"recording {i + 1}")) for i, r in enumerate(recs))
    for rec, name in zip(recs, names, strict=True):
        require_commands(rec, name)
    if not any(np.isfinite(r.wheel_rpm).any() for r in recs):
        raise DiagnoseError("no measured wheel speeds in the recordings: diagnose compares the "
                            "model's wheel speeds with measured ones")
    ev = _Evaluator(recs, rob)

    initial = calibration
    loc0 = localise(recs, _predictions(ev, initial), rob, names)
    rmse_initial = loc0.rmse_rpm
    say(f"initial model: wheel RMSE {rmse_initial:.3f} rpm, noise about {loc0.noise_rpm:.3f} rpm")
    for line in loc0.lines():
        say("  " + line)

    accepted = [e for e in EFFECTS if e in initial.effects.active()]
    free = list(_COEFFICIENTS) + [p for e in accepted for p in effect_parameters(e)
                                  if e != "deadband"]
    try:
        res = fit_parameters(recs, initial, rob, free,
                             x0={n: parameter_value(initial, n) for n in free},
                             pose_weight=1.0 if "slip" in accepted else 0.0, sources=names)
    except FitError as err:
        raise DiagnoseError(f"cannot refit the model on these recordings: {err}") from err
    current = with_parameters(initial, res.parameters)
    rmse_base = _rmse_per_recording(ev, current)[0]
    say(f"refit of {', '.join(free)}: wheel RMSE {rmse_base:.3f} rpm")
    noise = pooled_noise_sd(ev.wheel_residuals(ev.predict([current])[0]).values())
    if not noise > 0:
        raise DiagnoseError("cannot estimate the measurement noise (constant wheel speeds?)")
    noise2 = noise * noise
    baseline = current
    last_ci = dict(res.ci95)
    step_ci: list[dict[str, tuple[float, float]]] = []
    cur_free = [n for n in free if n != "deadband_rpm"]

    steps: list[DiagnoseStep] = []
    rejected: tuple[CandidateScore, ...] = ()
    wheel_cands = [c for c in candidates if c != "slip" and c not in accepted]
    pose_cands = [c for c in candidates if c == "slip" and c not in accepted]
    for channel, pool in (("wheel", wheel_cands), ("pose", pose_cands)):
        if channel == "pose":
            if not pool or not ev.has_pose() or not ev.set_pose_noise(current):
                continue
            scale2 = 1.0
        else:
            scale2 = noise2
        while pool and len(steps) < max_rounds:
            # the wheels pin A, B, C; on the pose channels only slip's parameters move
            moving = cur_free if channel == "wheel" else [
                n for n in cur_free if n.startswith("efficiency")]
            h0 = heldout_score(ev, current, moving, channel)
            s0 = _score(h0, scale2)
            if steps and channel == "wheel" and s0 > NOISE_FLOOR_SCORE:
                # refit the model just extended from where its fit stopped, so a candidate of
                # this round gets no credit for a search that merely went on further
                # (the cost is not smooth where a drive limit switches on, so a search may
                # stop early; restart it while it still gains 1 %, as a candidate's two
                # stages would)
                for _ in range(3):
                    try:
                        more = fit_parameters(
                            recs, current, rob, cur_free,
                            x0={n: parameter_value(current, n) for n in cur_free},
                            sources=names)
                    except (FitError, ConfigError):
                        break
                    sse_now = _rmse_per_recording(ev, current)[0] ** 2 * more.n_samples
                    if not more.sse < sse_now:
                        break
                    current = with_parameters(current, more.parameters)
                    last_ci = {**last_ci, **more.ci95}
                    if more.sse > 0.99 * sse_now:
                        break
                h0 = heldout_score(ev, current, moving, channel)
                s0 = _score(h0, scale2)
            say(f"round {len(steps) + 1} ({channel}): held-out score {s0:.3f} "
                "(mean square / noise^2; 1 = noise floor)")
            if s0 <= NOISE_FLOOR_SCORE:
                say("  the residual is at the noise floor: nothing significant is left")
                rejected = ()
                break
            scores: list[CandidateScore] = []
            fits: dict[str, _Fitted] = {}
            for effect in pool:
                try:
                    f = fit_candidate(ev, effect, current, cur_free, names, noise)
                    h1 = heldout_score(ev, f.calibration, f.free if channel == "wheel" else [
                        n for n in f.free if n.startswith("efficiency")], channel)
                except (FitError, ConfigError) as err:
                    scores.append(CandidateScore(effect, {}, {}, math.nan, math.nan, -math.inf,
                                                 -math.inf, note=str(err), in_sample=-math.inf))
                    say(f"  {effect:11s} failed: {err}")
                    continue
                s1 = _score(h1, scale2)
                explained = (s0 - s1) / max(s0 - 1.0, 1e-12)
                relative = (s0 - s1) / s0
                f0, f1 = h0.fit_ms / scale2, h1.fit_ms / scale2
                # no in-sample excess over the noise floor: nothing for a candidate to explain
                in_sample = (f0 - f1) / (f0 - 1.0) if f0 - 1.0 > MIN_EXCESS * f0 else 0.0
                fits[effect] = f
                ci = {n: f.ci95[n] for n in (*effect_parameters(effect),) if n in f.ci95}
                scores.append(CandidateScore(effect, _effect_values(f.calibration, effect), ci,
                                             math.sqrt(h1.fit_ms), math.sqrt(h1.heldout_ms),
                                             explained, relative, in_sample=in_sample))
                say(f"  {effect:11s} held-out score {s1:8.3f}  explains {100 * explained:6.1f} % "
                    f"of the excess ({100 * in_sample:6.1f} % in sample)  "
                    f"{_effect_values(f.calibration, effect)}")
            # explaining the gap held out AND in sample: the approximate held-out score of a
            # misspecified model is itself noisy, and a candidate that fits no better than
            # the baseline must not win on that noise
            ok = [s for s in scores if s.explained >= MIN_EXPLAINED
                  and s.in_sample >= MIN_EXPLAINED and s.relative >= MIN_RELATIVE]
            if not ok:
                rejected = tuple(scores)
                say("  no candidate explains a significant part of the gap")
                break
            win = max(ok, key=lambda s: s.relative)
            scores = [CandidateScore(**{**s.__dict__, "accepted": s is win}) for s in scores]
            f = fits[win.effect]
            before = _rmse_per_recording(ev, current)
            after = _rmse_per_recording(ev, f.calibration)
            steps.append(DiagnoseStep(
                win.effect, win.parameters, win.ci95, before[0], after[0], before[1], after[1],
                before[2], after[2], current, f.calibration, tuple(scores), f.warnings,
                win.explained))
            step_ci.append({**last_ci, **f.ci95})
            say(f"  -> {win.effect} added: wheel RMSE {before[0]:.3f} -> {after[0]:.3f} rpm")
            current = f.calibration
            cur_free = list(f.free)
            last_ci = {**last_ci, **f.ci95}
            pool = [c for c in pool if c != win.effect]
            rejected = ()

    final = _rmse_per_recording(ev, current)
    check = residual_check(final[3], noise)
    withdrawn: tuple[DiagnoseStep, ...] = ()
    if check.structured:
        # Structured residual remains: an effect that explained only part of its round's gap
        # may be the closest wrong effect standing in for something outside the library (a
        # dead time and a ramp both mimic a resonance's lag). Keep only the steps up to the
        # first one that did not explain CONFIRM_EXPLAINED of its gap; later steps were fitted
        # on top of it and go with it.
        keep = next((k for k, st in enumerate(steps) if st.explained < CONFIRM_EXPLAINED),
                    len(steps))
        if keep < len(steps):
            withdrawn = tuple(steps[keep:])
            steps = steps[:keep]
            current = steps[-1].calibration_after if steps else baseline
            last_ci = step_ci[keep - 1] if steps else dict(res.ci95)
            say("structured residual remains: withdrawn as partial stand-ins for something "
                "outside the library: " + ", ".join(
                    f"{st.effect} ({100 * st.explained:.0f} % of its gap)" for st in withdrawn))
            final = _rmse_per_recording(ev, current)
            check = residual_check(final[3], noise)
    loc1 = localise(recs, _predictions(ev, current), rob, names)
    unexplained = check.structured or bool(withdrawn)
    say(f"final model: wheel RMSE {final[0]:.3f} rpm = {check.ratio:.2f} x noise, lag-1 "
        f"autocorrelation {check.lag1_autocorrelation:.2f} -> "
        + ("structured residual no effect of the library explains (unexplained)"
           if unexplained else "what remains looks like noise"))
    info = dict(current.info)
    info.update({"method": "diagnose", "effects_added": [s.effect for s in steps],
                 "rmse_rpm": final[0], "unexplained": unexplained})
    cis = dict(last_ci)
    final_cal = replace(current, info=info, ci95={
        toml_key(k): (float(v[0]), float(v[1])) for k, v in cis.items()
        if all(map(math.isfinite, v))}, source="<diagnose>")
    return Diagnosis(tuple(steps), unexplained, rmse_initial, rmse_base, final[0], noise,
                     initial, baseline, final_cal, loc0, loc1, check, rejected, names, withdrawn)
