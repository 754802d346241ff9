"""Step 3, held-out scoring: how well a fitted model predicts data it was not fitted to."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ...errors import ConfigError, DiagnoseError, FitError
from ...model.calibration import Calibration
from ..fit import (
    DEFAULT_BOUNDS,
    fit_parameters,
    parameter_value,
    with_parameters,
)
from .localise import _Evaluator

_COEFFICIENTS = ("A", "B", "C")
# finite-difference steps of the held-out Jacobian: relative, with a floor in the unit
_FD_RELATIVE = 1e-4
_LOO_RCOND = 1e-4
_FD_FLOOR = {"A": 1e-3, "B": 1e-3, "C": 1e-2, "dead_time_s": 1e-4, "top_speed_rpm": 1e-2,
             "rate_limit_rpm_per_s": 1e-1, "deadband_rpm": 1e-2, "drive_lag_s": 1e-4,
             "controller_period_s": 1e-4, "breakaway_rpm_per_s": 1.0,
             "braking_limit_rpm_per_s": 1e-1, "coast_decel_rpm_per_s": 1e-1,
             "no_load_rpm": 1e-2, "windup_top_speed_rpm": 1e-2, "friction_rpm_per_s": 1.0,
             "drive_deadband_rpm": 1e-2}
#: Fewest recordings for leave-one-recording-out; with fewer, time blocks are held out.
MIN_RECORDINGS_LORO = 2
#: Residual evaluations of a fold's refit (from the full fit, a few trust-region steps).
FOLD_EVALUATIONS = 8
#: Folds of interleaved time blocks held out in turn when there are too few recordings ...
TIME_FOLDS = 4
#: ... with about this many blocks per recording (each block's measured samples in time order).
BLOCKS_PER_RECORDING = 40



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


def heldout_units(ev: _Evaluator, sizes: Mapping[int, int]) -> list[tuple[int, np.ndarray]]:
    """The units held out in turn, as (recording, sample mask): whole recordings when there are
    at least :data:`MIN_RECORDINGS_LORO`, else :data:`TIME_FOLDS` folds of short interleaved
    time blocks of each recording (about :data:`BLOCKS_PER_RECORDING` blocks, block ``b`` in fold
    ``b mod TIME_FOLDS``), so that every fold keeps part of each transient to fit on."""
    recs = [i for i in sorted(sizes) if sizes[i]]
    if len(recs) >= MIN_RECORDINGS_LORO:
        return [(i, np.ones(sizes[i], bool)) for i in recs]
    out = []
    for i in recs:
        length = max(4, sizes[i] // BLOCKS_PER_RECORDING)
        fold = (np.arange(sizes[i]) // length) % TIME_FOLDS
        out += [(i, fold == k) for k in range(TIME_FOLDS) if (fold == k).any()]
    return out


def _heldout_folds(ev: _Evaluator, cal: Calibration, free: list[str],
                   units: list[tuple[int, np.ndarray]], base: dict[int, np.ndarray],
                   fit_ms: float, n_all: int) -> HeldOut:
    """Held-out time folds, each refitted exactly: the fold's samples are removed from the
    recording (set to NaN), the free parameters refitted by least squares from the full fit,
    and the fold's samples predicted. (Within one recording the one-step approximation of
    leave-one-recording-out overshoots: the folds share the recording's few transients.)"""
    sq = {i: 0.0 for i in base}
    for i, mask in units:
        rec = ev.recs[i]
        wheel = rec.wheel_rpm.copy()
        finite = np.isfinite(wheel)
        flat = np.zeros(wheel.size, bool)
        flat[np.flatnonzero(finite.ravel())[mask]] = True
        held = flat.reshape(wheel.shape)
        wheel[held] = np.nan
        try:
            res = fit_parameters([rec.with_values(wheel_rpm=wheel)], cal, ev.robot, free,
                                 x0={n: parameter_value(cal, n) for n in free},
                                 max_evaluations=FOLD_EVALUATIONS)
            fold = with_parameters(cal, res.parameters)
        except (FitError, ConfigError):  # keep the full fit for this fold
            fold = cal
        pred = ev.predict([fold], subset=[i])[0][i][0]
        r = rec.wheel_rpm[held] - pred[held]
        sq[i] += float(r @ r)
    per = tuple(sq[i] / base[i].size for i in sorted(base) if base[i].size)
    return HeldOut(fit_ms, sum(sq.values()) / n_all, per)


def in_sample_ms(ev: _Evaluator, cal: Calibration, channel: str = "wheel") -> float:
    """In-sample mean square residual of ``cal`` on ``channel`` (:attr:`HeldOut.fit_ms`)."""
    base = ev.channel(ev.predict([cal])[0], channel)
    recs = [i for i in sorted(base) if base[i].size]
    n_all = sum(base[i].size for i in recs)
    return sum(float(base[i] @ base[i]) for i in recs) / n_all if n_all else float("nan")


def heldout_score(ev: _Evaluator, cal: Calibration, free: Sequence[str],
                  channel: str = "wheel") -> HeldOut:
    """Approximate held-out residual of a fitted model (package docstring, step 3).

    Each unit (:func:`heldout_units`: a recording, or a time block of a recording when there
    are too few recordings) is left out in turn: one Gauss-Newton step from the full fit using
    every other sample, then the model with those parameters simulated exactly and compared on
    the unit alone.

    Parameters
    ----------
    ev : _Evaluator
        The recordings.
    cal : Calibration
        The model fitted on all recordings.
    free : sequence of str
        Its fitted parameters, moved for each left-out unit (others stay fixed).
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
    units = heldout_units(ev, {i: base[i].size for i in recs})
    if not free or len(units) < 2:
        per = tuple(float(base[i] @ base[i]) / base[i].size for i in recs)
        return HeldOut(fit_ms, fit_ms, per)
    if channel == "wheel" and len(recs) < MIN_RECORDINGS_LORO:
        return _heldout_folds(ev, cal, free, units, base, fit_ms, n_all)
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
    for i, sl in units:
        keep = {k: np.ones(base[k].size, bool) for k in recs}
        keep[i] &= ~sl
        A = np.concatenate([J[k][keep[k]] for k in recs])
        b = np.concatenate([base[k][keep[k]] for k in recs])
        norms = np.linalg.norm(A, axis=0)
        norms[norms == 0] = 1.0
        # the one-step approximation holds for small moves only: directions the other
        # data barely determine are cut off (rcond), and each move is capped at half the
        # parameter's size, so a unit that alone pins a parameter cannot fling it away
        step = -np.linalg.lstsq(A / norms, b, rcond=_LOO_RCOND)[0] / norms
        cap = 0.5 * np.maximum(np.abs(x), 100.0 * h)
        xi = np.clip(x + np.clip(step, -cap, cap), lo, hi)
        try:
            left_out.append(with_parameters(cal, dict(zip(free, xi, strict=True))))
        except ConfigError:  # the step left the stable region: keep the full fit
            left_out.append(cal)
    sq = {i: 0.0 for i in recs}
    if len(units) == len(recs) and all(sl.all() for _, sl in units):
        # whole recordings: one batch with each recording's own left-out model
        per_rec = {i: c for (i, _), c in zip(units, left_out, strict=True)}
        batch = [per_rec.get(i, cal) for i in range(len(ev.recs))]
        held = ev.channel(ev.predict([batch], subset=recs)[0], channel)
        sq = {i: float(held[i] @ held[i]) for i in recs}
    else:
        for (i, sl), pred in zip(units,
                                 ev.predict(left_out, subset=sorted({u[0] for u in units})),
                                 strict=True):
            r = ev.channel(pred, channel)[i][sl]
            sq[i] += float(r @ r)
    per = tuple(sq[i] / base[i].size for i in recs)
    heldout_ms = sum(sq.values()) / n_all
    return HeldOut(fit_ms, heldout_ms, per)
