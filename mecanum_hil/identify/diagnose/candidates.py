"""Step 2, candidates: the library of effects, their start values from the data, their fit."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ...errors import ConfigError, DiagnoseError, FitError
from ...io.recording import Recording
from ...model.calibration import EFFECTS, EXCLUDES, Calibration
from ...model.kinematics import command_to_wheels
from ...model.robot import RobotProfile
from ...model.simulate import simulate
from ...prediction import model_start
from ..fit import (
    FitResult,
    fit_parameters,
    parameter_value,
    with_parameters,
)
from ..regimes import measured_differences
from .heldout import in_sample_ms
from .localise import _Evaluator, step_halves

CANDIDATES: tuple[str, ...] = ("dead_time", "saturation", "windup", "rate_limit", "deadband",
                               "wheel_gain", "controller_period", "drive_lag", "breakaway",
                               "friction", "drive_deadband", "braking_limit", "fast_decay",
                               "slip")
#: Parameters fitted on a grid (a deadband's cost is a staircase in it): held, not freed, in
#: the least squares that refit a model holding them.
GRID_FITTED: tuple[str, ...] = ("deadband_rpm", "drive_deadband_rpm")


def compatible(pool: Iterable[str], present: Iterable[str]) -> list[str]:
    """The candidates of ``pool`` that can join a model with the effects ``present``."""
    barred = {x for e in present for x in EXCLUDES.get(e, ())}
    return [c for c in pool if c not in barred]

_COEFFICIENTS = ("A", "B", "C")


def candidate_pool(names: Iterable[str] | None) -> tuple[str, ...]:
    """The effects a diagnosis tries: ``names`` (blank ones dropped, spaces stripped; ``None``:
    :data:`CANDIDATES`), each checked against the effect library. The one check of
    ``diagnose --candidates``, ``batch diagnose --candidates`` and :func:`~.selection.diagnose`.

    Raises
    ------
    DiagnoseError
        No effect named, or a name the library does not have.
    """
    if names is None:
        return CANDIDATES
    pool = tuple(n.strip() for n in names if n.strip())
    if not pool:
        raise DiagnoseError(f"--candidates names no effect; the library: {', '.join(EFFECTS)}")
    unknown = [n for n in pool if n not in EFFECTS]
    if unknown:
        raise DiagnoseError(f"unknown effect(s) {', '.join(map(repr, unknown))}; the library: "
                            f"{', '.join(EFFECTS)}")
    return pool


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
    """An effect's parameters as in :class:`Effects` (lists for gains and efficiency; an
    infinite one, a fast-decay drive without droop, left out as :meth:`Effects.active` does)."""
    out = {}
    for p in EFFECTS[effect].parameters:
        v = getattr(cal.effects, p)
        if isinstance(v, tuple):
            out[p] = [float(x) for x in v]
        elif math.isfinite(v):
            out[p] = float(v)
    return out



# --------------------------------------------------------------------------- candidates


def _smoothed(w: np.ndarray) -> np.ndarray:
    """Three-point moving average of each wheel over its measured samples: rows without a
    measurement (a recorded run's command rows) are skipped, not read as zeros; each wheel's
    first and last measured samples (the average would need padding there) are NaN."""
    out = np.full(w.shape, np.nan)
    for i in range(w.shape[1]):
        ok = np.flatnonzero(np.isfinite(w[:, i]))
        if ok.size >= 3:
            out[ok[1:-1], i] = (w[ok[:-2], i] + w[ok[1:-1], i] + w[ok[2:], i]) / 3.0
    return out


def _peak_rpm(recs: Sequence[Recording]) -> float:
    """The fastest smoothed measured wheel speed of the recordings [rpm]."""
    return max(float(np.nanmax(np.abs(_smoothed(r.wheel_rpm)))) for r in recs)


def _steepest_rpm_per_s(t: np.ndarray, w: np.ndarray) -> float:
    """The largest absolute slope of the smoothed wheel speeds between consecutive measured
    samples [rpm/s] (0 without two)."""
    d = np.abs(measured_differences(_smoothed(w), t))
    d = d[np.isfinite(d)]
    return float(d.max()) if d.size else 0.0


def _steepest_changes_rpm_per_s(t: np.ndarray, w: np.ndarray, noise_rpm: float,
                                window_s: float) -> tuple[float, float]:
    """The measured wheel speeds' changes over ``window_s`` [s] (from every measured sample to
    the first at least that much later: over consecutive samples of a 1 kHz log the encoder's
    noise alone makes thousands of rpm/s), as rates [rpm/s]: the largest deceleration towards
    rest where the speed is clear of it (beyond four noise levels, same sign at both ends), and
    the largest change in either direction, from rest too (the data's scale); 0 where there is
    none."""
    braking = scale = 0.0
    for i in range(w.shape[1]):
        ok = np.flatnonzero(np.isfinite(w[:, i]))
        if ok.size < 2:
            continue
        tt, v = t[ok], w[ok, i]
        j = np.searchsorted(tt, tt + window_s - 1e-12)
        a = np.flatnonzero(j < tt.size)
        b = j[a]
        if not a.size:
            continue
        slope = (v[b] - v[a]) / (tt[b] - tt[a])
        scale = max(scale, float(np.abs(slope).max()))
        clear = (np.abs(v[a]) > 4.0 * noise_rpm) & (np.abs(v[b]) > 4.0 * noise_rpm) & \
            (np.sign(v[a]) == np.sign(v[b]))
        toward = (-np.sign(v[a]) * slope)[clear]
        if toward.size:
            braking = max(braking, float(toward.max()))
    return braking, scale


def _latency_s(ev: _Evaluator, noise_rpm: float) -> float:
    """Model-free dead time guess: median delay from a large jump of a wheel target to the
    first measured departure of that wheel by more than four noise levels, less one sample."""
    lat, dts = [], []
    for r in ev.recs:
        tg = command_to_wheels(r.commands[:, 0], r.commands[:, 1], r.commands[:, 2], ev.robot.k)
        w, t = r.wheel_rpm, r.t_s
        period = r.measured_period_s
        if math.isfinite(period):
            dts.append(period)
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
    return round(max(float(np.median(lat)) - (float(np.median(dts)) if dts else 0.0), 0.0), 6)


#: Residual evaluations of the refit at each point of a grid (controller period), and at each
#: point of its coarse stage.
GRID_EVALUATIONS = 12
COARSE_EVALUATIONS = 3
#: Start values (as factors on the data-derived start) of effects whose cost has local minima.
MULTI_START: dict[str, tuple[float, ...]] = {"breakaway": (1.0, 2.0), "drive_lag": (1.0, 3.0)}
#: Effects whose search also restarts A, B, C from the engine's coarse grid (with the effect
#: held at its start): a ceiling moves the best coefficients far from a fit without it.
GRID_RESTART: tuple[str, ...] = ("saturation", "windup")


#: A fast-decay drive's no-load speed starts at this multiple of the fastest measured speed.
FAST_DECAY_NO_LOAD = 2.0

#: A braking limit starts at the steepest measured deceleration only when that is at least
#: this share of the steepest change of speed over the same window, and beyond what the noise
#: makes over it (else at the steepest change).
BRAKING_SEEN = 0.1


def _sample_period_s(ev: _Evaluator) -> float:
    """Median period of the measurements [s] (:attr:`Recording.measured_period_s`; of all rows
    where no recording has two measured ones)."""
    periods = [p for p in (r.measured_period_s for r in ev.recs) if math.isfinite(p)]
    if periods:
        return float(np.median(periods))
    return float(np.median(np.concatenate([np.diff(r.t_s) for r in ev.recs])))


def _rise_time_s(ev: _Evaluator, noise_rpm: float) -> float:
    """Model-free time from a large target jump to the wheel's first crossing of half of it
    (median over jumps and wheels; the sample period when no jump is seen)."""
    times = []
    for r in ev.recs:
        tg = command_to_wheels(r.commands[:, 0], r.commands[:, 1], r.commands[:, 2], ev.robot.k)
        for i in range(4):
            w = r.wheel_rpm[:, i]
            if not np.isfinite(w).any():
                continue
            jumps = np.flatnonzero(np.abs(np.diff(tg[:, i])) >= max(20.0 * noise_rpm, 5.0)) + 1
            if not jumps.size and abs(tg[0, i]) > max(20.0 * noise_rpm, 5.0):
                jumps = np.array([0])  # the recording starts with the step
            for j in jumps:
                half = 0.5 * (tg[j, i] + tg[max(j - 1, 0), i] if j else tg[j, i])
                sgn = np.sign(tg[j, i] - (tg[j - 1, i] if j else 0.0))
                hit = np.flatnonzero((np.arange(w.size) >= j) & (sgn * (w - half) >= 0))
                if hit.size:
                    times.append(r.t_s[hit[0]] - r.t_s[j])
    return float(np.median(times)) if times else _sample_period_s(ev)


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
        best = max([1.0] + [_steepest_rpm_per_s(r.t_s, r.wheel_rpm) for r in recs])
        return {"rate_limit_rpm_per_s": best}
    if effect == "saturation":
        peak = _peak_rpm(recs)
        return {"top_speed_rpm": 1.02 * peak}
    if effect == "windup":
        # the clamped output holds the wheel below its top speed: an overshoot's peak too
        return {"windup_top_speed_rpm": 1.02 * _peak_rpm(recs)}
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
    if effect == "drive_lag":
        # a second lag is a fraction of the rise time; the data's own time scale
        return {"drive_lag_s": max(0.15 * _rise_time_s(ev, noise_rpm), _sample_period_s(ev))}
    if effect in ("breakaway", "friction"):
        # read off the data in fit_candidate (needs A, B, C)
        return {effect_parameters(effect)[0]: 0.0}
    if effect == "fast_decay":
        # a coasting wheel slows at the friction (the steepest measured deceleration, as for
        # a braking limit); the push falls to nothing well above the fastest measured speed
        peak = _peak_rpm(recs)
        return {"coast_decel_rpm_per_s": _start_values("braking_limit", ev, noise_rpm)[
            "braking_limit_rpm_per_s"], "no_load_rpm": FAST_DECAY_NO_LOAD * max(peak, 1.0)}
    if effect == "braking_limit":
        # a drive that cannot brake harder caps the measured deceleration: start at the
        # steepest one, over the data's own time scale (the rise time, at least two samples)
        window = max(_rise_time_s(ev, noise_rpm), 2.0 * _sample_period_s(ev))
        changes = [_steepest_changes_rpm_per_s(r.t_s, r.wheel_rpm, noise_rpm, window)
                   for r in recs]
        best = max([0.0] + [braking for braking, _ in changes])
        scale = max([1.0] + [change for _, change in changes])
        # the noise alone, four standard deviations of a difference over the window
        floor = 4.0 * math.sqrt(2.0) * noise_rpm / window
        if best < max(BRAKING_SEEN * scale, floor):
            # no wheel is seen slowing (only noise or a creeping settle against the rise):
            # the steepest change of speed is the data's scale; a limit far below it would
            # bind on the first stop the model makes
            best = scale
        return {"braking_limit_rpm_per_s": best}
    if effect == "controller_period":
        return {"controller_period_s": _sample_period_s(ev)}
    return {}


def _corner_starts(effect: str, ev: _Evaluator) -> list[dict[str, float]]:
    """Further start values of an effect for the grid restart from a corner
    (:func:`_searched`): a ceiling at the fastest smoothed measured speed itself."""
    if effect == "saturation":
        return [{"top_speed_rpm": _peak_rpm(ev.recs)}]
    if effect == "windup":
        return [{"windup_top_speed_rpm": _peak_rpm(ev.recs)}]
    return []


def _breakaway_start(ev: _Evaluator, cal: Calibration, noise_rpm: float) -> float:
    """The drive a wheel at rest felt when it started to move: the PI output of ``cal`` at the
    measured time the wheel first left rest after a target jump (``A u + C u t``)."""
    lat = _latency_s(ev, noise_rpm) + _sample_period_s(ev)
    tg = max((float(np.nanmax(np.abs(command_to_wheels(
        r.commands[:, 0], r.commands[:, 1], r.commands[:, 2], ev.robot.k)))) for r in ev.recs),
        default=0.0)
    return max(0.5 * (cal.A * tg + cal.C * tg * lat), 1.0)


def _level_offset_rpm(ev: _Evaluator) -> float:
    """How far below its target a held wheel settles, beyond a share of the target [rpm]: the
    least-squares ``b`` of ``|y| = a |u| - b`` over the second half of every step of a
    target of at least 10 rpm (:func:`.localise.step_halves`), all measured wheels pooled (0
    without two such levels)."""
    xs, ys = [], []
    for w in range(4):
        for target, _, y in step_halves(ev.recs, ev.robot, w):
            xs.append(abs(target))
            ys.append(float(np.mean(y)) * math.copysign(1.0, target))
    if len(set(np.round(xs, 6))) < 2:
        return 0.0
    _, offset = np.polyfit(np.asarray(xs), np.asarray(ys), 1)
    return max(-float(offset), 0.0)


def _friction_start(ev: _Evaluator, cal: Calibration, noise_rpm: float) -> float:
    """A Coulomb friction read off the data [rpm/s]: the drive that holds a proportional loop's
    level offset (``(A + B) b``, :func:`_level_offset_rpm`), or, where the levels show none
    beyond the noise (an integral removes it), half the drive a wheel at rest felt when it
    started to move."""
    offset = _level_offset_rpm(ev)
    if offset > noise_rpm:
        return (cal.A + cal.B) * offset
    return 0.5 * _breakaway_start(ev, cal, noise_rpm)


def _candidate_bounds(effect: str, guess: Mapping[str, float],
                      duration_s: float = 2.0) -> dict[str, tuple[float, float]]:
    """Finite search ranges from the data: an effect that is absent drives its parameter
    towards "absent" (an infinite ceiling or ramp limit), which a bounded search reaches in a
    few steps instead of chasing it through hundreds of evaluations; a dead time is looked for
    up to a quarter of the recordings' median duration (at most 0.5 s)."""
    if effect == "dead_time":
        return {"dead_time_s": (0.0, min(0.5, 0.25 * duration_s))}
    if effect in ("saturation", "windup"):
        name = effect_parameters(effect)[0]
        g = guess[name]
        return {name: (0.2 * g, 3.0 * g)}
    if effect == "rate_limit":
        g = guess["rate_limit_rpm_per_s"]
        return {"rate_limit_rpm_per_s": (min(1.0, 0.05 * g), 20.0 * g)}
    if effect == "wheel_gain":
        return {f"gains[{i}]": (0.1, 3.0) for i in range(4)}
    if effect == "slip":
        return {f"efficiency[{i}]": (0.05, 2.0) for i in range(3)}
    if effect == "drive_lag":
        g = guess["drive_lag_s"]
        return {"drive_lag_s": (0.0, max(50.0 * g, 0.05))}
    if effect in ("breakaway", "friction"):
        name = effect_parameters(effect)[0]
        g = guess[name]
        return {name: (0.0, max(20.0 * g, 100.0))}
    if effect == "braking_limit":
        g = guess["braking_limit_rpm_per_s"]
        return {"braking_limit_rpm_per_s": (min(1.0, 0.05 * g), 20.0 * g)}
    if effect == "fast_decay":
        g = guess["coast_decel_rpm_per_s"]
        peak = guess["no_load_rpm"] / FAST_DECAY_NO_LOAD
        return {"coast_decel_rpm_per_s": (0.0, 20.0 * g),
                "no_load_rpm": (1.05 * peak, 100.0 * peak)}
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
        95 % intervals of its parameters (engine names), clipped to their admissible ranges;
        ``(nan, nan)`` where the data cannot bound the parameter.
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
    #: Why the candidate is the model without the effect (no fit in its range did better).
    absent: str = ""


def _deadband_grid(ev: _Evaluator, cal: Calibration, values: np.ndarray,
                   name: str = "deadband_rpm") -> tuple[np.ndarray, int]:
    """Wheel SSE for each value of the deadband ``name`` (A, B, C held), on the recordings it
    can change."""
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
    cals = [with_parameters(cal, {name: float(v)}) for v in values]
    sse = np.empty(values.size)
    n = 0
    for k, pred in enumerate(ev.predict(cals, subset=touched)):
        res = ev.channel(pred, "wheel")
        sse[k] = sum(float(r @ r) for r in res.values())
        n = sum(r.size for r in res.values())
    return sse, n


def _refit_held(ev: _Evaluator, cal: Calibration, free: Sequence[str],
                sources: Sequence[str]) -> tuple[Calibration, FitResult]:
    """``free`` refitted by least squares from ``cal``, the rest (a deadband) held."""
    res = fit_parameters(ev.recs, cal, ev.robot, list(free),
                         x0={n: parameter_value(cal, n) for n in free}, sources=sources)
    return with_parameters(cal, res.parameters), res


#: Most switch-off levels :func:`_switch_off_levels` refits the coefficients for.
SWITCH_OFF_LEVELS = 6


def _switch_off_levels(ev: _Evaluator, base: Calibration, base_free: Sequence[str],
                       sources: Sequence[str], targets: np.ndarray, reach: float
                       ) -> tuple[float, Calibration, FitResult]:
    """The drive deadband among the levels that switch off a different set of the measured
    small targets (just above each distinct one up to ``reach`` [rpm], at most
    :data:`SWITCH_OFF_LEVELS` of them, spread over the quantiles), each with ``base_free``
    refitted: the lowest in-sample error wins; returns it, its model and its fit."""
    levels = np.unique(np.round(targets[targets <= reach], 3))
    if levels.size == 0:
        raise FitError(f"no wheel target at or below {reach:.4g} rpm: a drive deadband cannot "
                       "be seen")
    if levels.size > SWITCH_OFF_LEVELS:
        levels = np.unique(np.quantile(levels, np.linspace(0.0, 1.0, SWITCH_OFF_LEVELS),
                                       method="nearest"))
    best: tuple[float, float, Calibration, FitResult] | None = None
    for level in levels:
        db = float(level) + 0.05
        try:
            cal, res = _refit_held(ev, with_parameters(base, {"drive_deadband_rpm": db}),
                                   base_free, sources)
        except (FitError, ConfigError):
            continue
        ms = in_sample_ms(ev, cal)
        if best is None or ms < best[0]:
            best = (ms, db, cal, res)
    if best is None:
        raise FitError("no drive deadband level could be fitted")
    return best[1], best[2], best[3]


def _fit_deadband(ev: _Evaluator, base: Calibration, base_free: Sequence[str],
                  sources: Sequence[str], effect: str = "deadband") -> _Fitted:
    """A deadband (``deadband`` or ``drive_deadband``) by a coarse-to-fine grid (A, B, C
    held), then the rest by least squares, then the grid again; the interval is the set of
    grid values whose SSE is within the 95 % F-test bound of the best."""
    name = effect_parameters(effect)[0]
    targets = np.concatenate([np.abs(command_to_wheels(
        r.commands[:, 0], r.commands[:, 1], r.commands[:, 2], ev.robot.k)).ravel()
        for r in ev.recs])
    targets = targets[targets > 1e-9]
    reach = float(0.3 * targets.max()) if targets.size else 0.0
    top = min(reach, 30.0)
    if top <= 0.5:
        raise FitError("no small wheel targets in the data: a deadband cannot be seen")
    cal = base
    # 1 rpm steps up to 30 rpm; a fast robot's larger targets extend the scan (30 steps more)
    wide = np.linspace(30.0, reach, 31)[1:] if reach > 60.0 else np.empty(0)

    def scan(cal: Calibration, center: float | None) -> tuple[float, tuple[float, float]]:
        coarse = np.concatenate([np.arange(0.0, top + 1e-9, 1.0), wide]) if center is None else \
            np.arange(max(center - 1.5, 0.0), center + 1.5 + 1e-9, 0.1)
        sse, n = _deadband_grid(ev, cal, coarse, name)
        best = float(coarse[int(np.argmin(sse))])
        if center is None:
            return scan(cal, best)
        lim = sse.min() * (1.0 + 3.84 / max(n - len(base_free) - 1, 1))
        ok = coarse[sse <= lim]
        return best, (float(ok.min()), float(ok.max()))

    if effect == "drive_deadband":
        # how fast a wheel coasts is the motor's pole, which coefficients fitted with the drive
        # always on need not know: each switch-off level is tried with them refitted, and the
        # level found on the fine grid
        db, cal, _ = _switch_off_levels(ev, base, base_free, sources, targets, reach)
        db, _ = scan(cal, db)
    else:
        db, _ = scan(cal, None)
    cal, res = _refit_held(ev, with_parameters(cal, {name: db}), base_free, sources)
    db, ci = scan(cal, db)
    cal = with_parameters(cal, {name: db})
    return _Fitted(effect, cal, tuple(base_free), {**res.ci95, name: ci}, res.warnings)


def _fit_controller_period(ev: _Evaluator, base: Calibration, base_free: Sequence[str],
                           sources: Sequence[str]) -> _Fitted:
    """The controller period by a grid (the cost jumps where a tick crosses a sample, so least
    squares cannot follow it): half sample periods up to 16 samples, each briefly refitted, the
    best three and a finer grid around the best refitted quickly, the best converged. The
    ticks' phase comes from the recordings' ``controller_time_s`` (the controller's clock)
    where they have it. Held fixed during the held-out evaluation."""
    dt = _sample_period_s(ev)
    dur = float(np.median([r.t_s[-1] - r.t_s[0] for r in ev.recs]))

    def refit(period: float, evaluations: int = 0) -> tuple[float, Calibration, FitResult]:
        cal = with_parameters(base, {"controller_period_s": period})
        res = fit_parameters(ev.recs, cal, ev.robot, list(base_free),
                             x0={n: parameter_value(cal, n) for n in base_free},
                             sources=sources, max_evaluations=evaluations or GRID_EVALUATIONS)
        return res.sse, with_parameters(cal, res.parameters), res

    # a dense grid of half sample periods up to 16 samples (a tenth of the recordings at most),
    # each scored after a brief refit; the best few refitted further, then a finer grid
    top = max(min(16.0 * dt, dur / 10.0), dt)
    coarse = np.arange(0.5 * dt, top + 1e-12, 0.5 * dt)
    sse0 = []
    for v in coarse:
        # a few evaluations each: the coefficients fitted without the effect are off enough
        # that the true period scores badly with them held
        try:
            sse0.append(refit(float(v), COARSE_EVALUATIONS)[0])
        except (FitError, ConfigError):
            sse0.append(math.inf)
    trials = {}
    for v in coarse[np.argsort(sse0)[:3]]:
        try:
            trials[float(v)] = refit(float(v))
        except (FitError, ConfigError):
            continue
    if not trials:
        raise FitError("no controller period could be fitted")
    best = min(trials, key=lambda v: trials[v][0])
    fine = np.arange(max(best - 0.5 * dt, 1e-4), best + 0.5 * dt + 1e-9,
                     max(dt / 8.0, 2.5e-4))
    for v in fine:
        if all(abs(float(v) - k) > 1e-9 for k in trials):
            try:
                trials[float(v)] = refit(float(v))
            except (FitError, ConfigError):
                continue
    best = min(trials, key=lambda v: trials[v][0])
    sse, cal, res = trials[best]
    # the grid's refits were quick; converge at the best point
    full = fit_parameters(ev.recs, cal, ev.robot, list(base_free),
                          x0={n: parameter_value(cal, n) for n in base_free}, sources=sources)
    if full.sse <= sse:
        sse, cal, res = full.sse, with_parameters(cal, full.parameters), full
    n = res.n_samples
    lim = sse * (1.0 + 3.84 / max(n - len(base_free) - 1, 1))
    ok = [v for v, tr in trials.items() if tr[0] <= lim] or [best]
    warnings = res.warnings
    if best >= top - 1e-9:
        warnings += (f"controller_period_s = {best:.4g} is at the edge of its search range "
                     f"(up to {top:.4g} s, from the sample period)",)
    return _Fitted("controller_period", cal, tuple(base_free),
                   {**res.ci95, "controller_period_s": (min(ok), max(ok))}, warnings)


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
    if effect in ("deadband", "drive_deadband"):
        return _fit_deadband(ev, base, base_free, sources, effect)
    if effect == "controller_period":
        return _fit_controller_period(ev, base, base_free, sources)
    new = effect_parameters(effect)
    guess = _start_values(effect, ev, noise_rpm)
    if effect == "breakaway":
        guess = {"breakaway_rpm_per_s": _breakaway_start(ev, base, noise_rpm)}
    elif effect == "friction":
        guess = {"friction_rpm_per_s": _friction_start(ev, base, noise_rpm)}
    bounds = _candidate_bounds(effect, guess, float(np.median(
        [r.t_s[-1] - r.t_s[0] for r in ev.recs])))
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
    try:
        fitted = _searched(ev, effect, base, cal, guess, bounds, base_free, free, sources,
                           two_stage)
    except (FitError, ConfigError) as err:
        fitted, failure = None, err
    # a kinked cost (a limit that switches on, a delay) has local minima: the searches from
    # the data's start values can end worse than the model without the effect, which is a
    # member of the family (the effect absent). Then a search from the model as it is, with
    # the effect where it does least within its range (monotone: it never ends above its
    # start); and if that too ends worse, the candidate is the model without it
    ms = in_sample_ms(ev, fitted.calibration) if fitted is not None else math.inf
    ms_base = in_sample_ms(ev, base)
    if fitted is not None and ms <= ms_base:
        return _resolved(ev, fitted, base, base_free, noise_rpm)
    least = with_parameters(base, _least_values(effect, bounds))
    try:
        with np.errstate(over="ignore", invalid="ignore"):
            res = fit_parameters(ev.recs, least, ev.robot, free,
                                 x0={n: parameter_value(least, n) for n in free},
                                 bounds=bounds, sources=sources)
        floor = _Fitted(effect, with_parameters(least, res.parameters), tuple(free),
                        dict(res.ci95),
                        res.warnings + tuple(_edge_warnings(res.parameters, bounds)))
        ms_floor = in_sample_ms(ev, floor.calibration)
    except (FitError, ConfigError):
        floor, ms_floor = None, math.inf
    if ms_floor < min(ms, ms_base):
        return _resolved(ev, floor, base, base_free, noise_rpm)
    if fitted is None and floor is None:
        raise failure
    return _Fitted(effect, base, tuple(base_free), {}, (), absent=(
        "no fit within its search range does better in sample than the model without it"))


#: A set-point ramp is named only when it lasts at least this many sample periods over a
#: typical target jump: a shorter one is what the speed reading's own lag (counts over the last
#: period: half a period late) looks like, which the data cannot tell from a ramp.
MIN_RAMP_SAMPLES = 2.0


def _typical_jump_rpm(ev: _Evaluator, noise_rpm: float) -> float:
    """Median size of the wheel targets' jumps on the measured wheels [rpm] (jumps of at least
    ``max(20 noise, 5 rpm)``, as :func:`_rise_time_s`); NaN without one."""
    jumps = []
    for r in ev.recs:
        tg = command_to_wheels(r.commands[:, 0], r.commands[:, 1], r.commands[:, 2], ev.robot.k)
        measured = np.isfinite(r.wheel_rpm).any(axis=0)
        # a recording that starts with its target counts it as a jump from rest
        d = np.abs(np.diff(tg[:, measured], axis=0, prepend=0.0))
        jumps.extend(d[d >= max(20.0 * noise_rpm, 5.0)].tolist())
    return float(np.median(jumps)) if jumps else math.nan


def _fine_wheel_rpm(rec: Recording, calibration: Calibration, robot: RobotProfile
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The model's measured wheels on a recording's own commands (held from their rows) on a
    1 ms grid (the recording's own where finer), started as
    :func:`~mecanum_hil.prediction.predict` starts it (:func:`~mecanum_hil.prediction.model_start`):
    times [s], speeds (T, wheels) [rpm]."""
    measured = np.isfinite(rec.wheel_rpm).any(axis=0)
    dt = min(1e-3, float(np.median(np.diff(rec.t_s))))
    t = np.arange(rec.t_s[0], rec.t_s[-1] + 0.5 * dt, dt)
    rows = np.searchsorted(rec.t_s, t, side="right") - 1
    y = simulate(rec.commands[rows], t, calibration, robot,
                 **model_start(rec, calibration, robot)).wheel_rpm[0]
    return t, y[:, measured]


def _first_crossing_s(t: np.ndarray, y: np.ndarray, level: float, sign: float) -> float:
    """First time [s] ``y`` reaches ``level`` going in direction ``-sign`` (interpolated
    linearly between samples); inf when it never does."""
    hit = np.flatnonzero(sign * (y - level) <= 0.0)
    if not hit.size:
        return math.inf
    k = int(hit[0])
    if k == 0:
        return float(t[0])
    frac = (y[k - 1] - level) / (y[k - 1] - y[k])
    return float(t[k - 1] + frac * (t[k] - t[k - 1]))


def braking_delay_s(recordings: Sequence[Recording], calibration: Calibration,
                    robot: RobotProfile) -> float:
    """How much later a braking limit makes the model's wheels slow down [s], on the
    recordings' own commands.

    The model with and without its braking limit runs each recording (1 ms grid,
    :func:`_fine_wheel_rpm`). Wherever a measured wheel slows at the limit, the slowdown of
    the model without it that this phase cuts short (from the phase's start to where that
    model's speed turns: a stop, a reversal, an overshoot's fall) is timed at 10 %, 20 %, ...
    90 % of its drop in both models; the delay is the largest difference over
    all of them. 0 when the calibration has no finite braking limit or no wheel reaches it;
    infinite when the limited model never gets as far as the other.
    """
    limit = calibration.effects.braking_limit_rpm_per_s
    if not math.isfinite(limit):
        return 0.0
    free = with_parameters(calibration, {"braking_limit_rpm_per_s": math.inf})
    delay = 0.0
    for rec in recordings:
        if len(rec.t_s) < 2 or not np.isfinite(rec.wheel_rpm).any():
            continue
        t, limited = _fine_wheel_rpm(rec, calibration, robot)
        _, unlimited = _fine_wheel_rpm(rec, free, robot)
        for yl, yf in zip(limited.T, unlimited.T, strict=True):
            slowing = -np.sign(yl[:-1]) * np.diff(yl) / np.diff(t)
            at = (np.abs(slowing - limit) <= 1e-6 * limit) & (yl[:-1] != 0.0)
            starts = np.flatnonzero(np.diff(np.concatenate(([0], at.astype(np.int8)))) == 1)
            for s in starts:
                sign = np.sign(yf[s])
                turns = np.flatnonzero(sign * np.diff(yf[s:]) >= 0.0)
                end = s + (int(turns[0]) if turns.size else yf.size - 1 - s)
                hi, lo = yf[s], yf[end]
                if sign * (hi - lo) <= 0.0:
                    continue
                for level in hi + (lo - hi) * np.linspace(0.1, 0.9, 9):
                    tf = _first_crossing_s(t[s:end + 1], yf[s:end + 1], level, sign)
                    tl = _first_crossing_s(t[s:], yl[s:], level, sign)
                    delay = max(delay, tl - tf)
    return delay


def _resolved(ev: _Evaluator, fitted: _Fitted, base: Calibration, base_free: Sequence[str],
              noise_rpm: float) -> _Fitted:
    """``fitted``, or the model without its effect when the data cannot resolve it: a ramp
    limit shorter than :data:`MIN_RAMP_SAMPLES` sample periods over a typical jump, or a
    braking limit that delays the model's slowdowns on the recordings by less than that
    (:func:`braking_delay_s`: a stop that starts late by a latency, or is read half a period
    late, looks the same)."""
    if fitted.effect == "braking_limit":
        period = _sample_period_s(ev)
        delay = braking_delay_s(ev.recs, fitted.calibration, ev.robot)
        if not (math.isfinite(period) and period > 0) or delay >= MIN_RAMP_SAMPLES * period:
            return fitted
        limit = fitted.calibration.effects.braking_limit_rpm_per_s
        return _Fitted(fitted.effect, base, tuple(base_free), {}, (), absent=(
            f"the limit it fits ({limit:.4g} rpm/s) delays the wheels' slowdowns by "
            f"{1000 * delay:.3g} ms at most, less than {MIN_RAMP_SAMPLES:g} samples "
            f"({1000 * period:.3g} ms each): the data cannot tell it from a stop that starts "
            "late (a latency) or the speed reading's own lag"))
    if fitted.effect != "rate_limit":
        return fitted
    rate = fitted.calibration.effects.rate_limit_rpm_per_s
    jump, period = _typical_jump_rpm(ev, noise_rpm), _sample_period_s(ev)
    if not (math.isfinite(jump) and math.isfinite(rate) and rate > 0
            and math.isfinite(period) and period > 0):
        return fitted
    if jump / rate >= MIN_RAMP_SAMPLES * period:
        return fitted
    return _Fitted(fitted.effect, base, tuple(base_free), {}, (), absent=(
        f"the ramp it fits ({1000 * jump / rate:.3g} ms over a typical jump of {jump:.4g} rpm) "
        f"is shorter than {MIN_RAMP_SAMPLES:g} samples ({1000 * period:.3g} ms each): the data "
        "cannot tell it from the speed reading's own lag"))


def _least_values(effect: str, bounds: Mapping[str, tuple[float, float]]
                   ) -> dict[str, float]:
    """An effect's parameters where, within its search range, it does least: no delay, lag or
    breakaway (0), unit gains and efficiencies, the highest ceiling, ramp limit, braking limit
    and fast-decay friction and no-load speed (which may still act: a ramp limit on the
    set-point acts on every step)."""
    out = {}
    for n in effect_parameters(effect):
        lo, hi = bounds.get(n, (-math.inf, math.inf))
        if n.startswith(("gains", "efficiency")):
            v = 1.0
        elif n in ("top_speed_rpm", "windup_top_speed_rpm", "rate_limit_rpm_per_s",
                   "braking_limit_rpm_per_s", "coast_decel_rpm_per_s", "no_load_rpm"):
            v = hi
        else:
            v = 0.0
        out[n] = float(np.clip(v, lo, hi))
    return out


def _searched(ev: _Evaluator, effect: str, base: Calibration, cal: Calibration,
              guess: Mapping[str, float], bounds: Mapping[str, tuple[float, float]],
              base_free: Sequence[str], free: Sequence[str], sources: Sequence[str],
              two_stage: bool) -> _Fitted:
    """The candidate's searches from the data's start values (:func:`fit_candidate`)."""
    if degenerate(base):
        # from a corner no local search leaves (C -> 0 mimics a ceiling with a lower gain):
        # the engine's coarse grid restarts A, B, C with the effect at its start, and the
        # joint search runs from each of the grid's best minima; the search from where the
        # model is competes with them. A ceiling is also held at the fastest measured speed
        # itself: 2 % above a plateau its misfit on a loop that reaches the plateau can
        # outweigh the corner's, and the grid then offers only corners, where the ceiling
        # never engages and its search cannot move
        # (the searches differ only in free parameters: each result is a calibration of cal's)
        starts = [cal] + [with_parameters(cal, values) for values in _corner_starts(effect, ev)]
        res = _best_fit([
            *(lambda c=c: fit_parameters(ev.recs, c, ev.robot, free, x0={
                n: parameter_value(c, n) for n in free if n not in _COEFFICIENTS},
                bounds=bounds, sources=sources) for c in starts),
            lambda: fit_parameters(ev.recs, cal, ev.robot, free,
                                   x0={n: parameter_value(cal, n) for n in free},
                                   bounds=bounds, sources=sources)])
        return _Fitted(effect, with_parameters(cal, res.parameters), tuple(free),
                       dict(res.ci95), res.warnings)
    # the drive's own dynamics change the loop's character (ringing, overshoot): their cost
    # has local minima, so the search also starts from a second value read off the data
    scales = MULTI_START.get(effect, (1.0,))
    cals = [with_parameters(base, {n: v * f for n, v in guess.items()}) for f in scales]

    def search(cal: Calibration) -> tuple[Calibration, FitResult]:
        if two_stage:
            x0 = {n: parameter_value(cal, n) for n in base_free}
            first = fit_parameters(ev.recs, cal, ev.robot, list(base_free), x0=x0,
                                   sources=sources)
            cal = with_parameters(cal, first.parameters)
        res = fit_parameters(ev.recs, cal, ev.robot, free,
                             x0={n: parameter_value(cal, n) for n in free},
                             bounds=bounds, sources=sources)
        return cal, res

    best: tuple[Calibration, FitResult] | None = None
    errors: list[Exception] = []
    for c in cals:
        try:
            # a search may visit a model that diverges (a huge breakaway, a long lag): its
            # overflow only makes that point's cost infinite, which the search rejects
            with np.errstate(over="ignore", invalid="ignore"):
                got = search(c)
        except (FitError, ConfigError) as err:
            errors.append(err)
            continue
        if best is None or got[1].sse < best[1].sse:
            best = got
    if effect in GRID_RESTART:
        # a fit without a ceiling compromises (a slow, low-gain loop that never reaches the
        # ceiling's speeds fast); no local search from there finds the loop that runs into
        # the ceiling: the engine's coarse grid restarts A, B, C with the ceiling held at its
        # start, then the joint search runs from there, and competes with the searches above
        held = with_parameters(base, guess)
        try:
            with np.errstate(over="ignore", invalid="ignore"):
                grid = fit_parameters(ev.recs, held, ev.robot, list(base_free), x0={
                    n: parameter_value(held, n) for n in base_free if n not in _COEFFICIENTS},
                    sources=sources)
                held = with_parameters(held, grid.parameters)
                got = (held, fit_parameters(ev.recs, held, ev.robot, free,
                                            x0={n: parameter_value(held, n) for n in free},
                                            bounds=bounds, sources=sources))
        except (FitError, ConfigError) as err:
            errors.append(err)
        else:
            if best is None or got[1].sse < best[1].sse:
                best = got
    if best is None:
        raise errors[0]
    cal, res = best
    warnings = res.warnings + tuple(_edge_warnings(res.parameters, bounds))
    return _Fitted(effect, with_parameters(cal, res.parameters), tuple(free), dict(res.ci95),
                   warnings)


def _edge_warnings(values: Mapping[str, float], bounds: Mapping[str, tuple[float, float]]):
    """A parameter that ends on the upper edge of its data-derived search range: say so."""
    for n, (_, hi) in bounds.items():
        v = values.get(n)
        if v is not None and math.isfinite(hi) and v >= hi * (1.0 - 1e-6):
            yield (f"{n} = {v:.4g} is at the upper edge {hi:.4g} of its search range "
                   "(derived from the data): the data favour a larger value")


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


