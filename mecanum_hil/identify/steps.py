"""Every step of a recording, one by one: time to half the step and the level it settles at.

A long recording (a staircase of 20 steps, reversals, signed set-points) is judged step by step,
not by one global curve. :func:`split_steps` cuts each wheel's target into steps at its jumps;
:func:`step_figures` measures one wheel-speed series (measured or a model's prediction at the
same sample times) on those steps:

* **step**: from the first row whose wheel target differs from the previous row's by more than
  the jump threshold (``max(JUMP_MIN_RPM, JUMP_SHARE * max |target|)``) up to the next such row
  (or the end); the recording's start counts as a step when its first target is not zero. A
  target is in force from its row's ``t_s`` (docs/conventions.md), so a step starts at
  ``t_s`` of its first row.
* **level**: the mean of the series over the last quarter of the step's samples
  (:data:`LEVEL_SHARE`; at least one sample), i.e. what the wheel settled at.
* **time to 50 %**: from the step's start to the first crossing of the midpoint between the level
  before (the previous step's level by the same rule; for the first step of a recording the
  series' value at its start) and this step's level, linearly interpolated between samples.
  Each series is measured against its *own* levels, so a model whose level is off is judged on
  its timing separately (a level that misses the target, by a ceiling or a proportional-only
  loop, would otherwise never cross half the way to the target). NaN when the step moves the
  series by less than :data:`MIN_MOVE` of the target change or four noise levels (a deadband:
  the wheel did not move), or when the crossing is not found.

Pure numpy, no I/O; ``diagnose --report`` and the tests use it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

#: Smallest target jump that starts a step [rpm], and as a share of the largest |target| [-].
JUMP_MIN_RPM = 1.0
JUMP_SHARE = 0.02
#: Share of a step's samples, at its end, over which its level is averaged [-].
LEVEL_SHARE = 0.25
#: A step whose level moves by less than this share of its target change (or four noise
#: levels) has no time to 50 % [-].
MIN_MOVE = 0.2


@dataclass(frozen=True)
class Step:
    """One step of one wheel's target.

    Attributes
    ----------
    wheel : int
        Wheel index, 0-based (0 FL, 1 FR, 2 RL, 3 RR).
    index : int
        Number of the step within its wheel, 0-based.
    start, stop : int
        Rows of the step: ``start`` (first row of the new target) to ``stop`` (exclusive).
    t_start_s, t_end_s : float
        ``t_s`` of the first row and of the last row of the step [s].
    before_rpm, target_rpm : float
        The target before the step and during it [rpm].
    """

    wheel: int
    index: int
    start: int
    stop: int
    t_start_s: float
    t_end_s: float
    before_rpm: float
    target_rpm: float


@dataclass(frozen=True)
class StepFigures:
    """One series on one step.

    Attributes
    ----------
    t50_s : float
        Time from the step's start to the crossing of half the way from the level before to the
        level reached [s]; NaN when not defined (see the module docstring).
    level_rpm : float
        Mean over the last quarter of the step [rpm]; NaN without samples.
    """

    t50_s: float
    level_rpm: float


def split_steps(t_s: np.ndarray, target_rpm: np.ndarray,
                wheels: Sequence[int] | None = None) -> list[Step]:
    """The steps of each wheel's target (see the module docstring).

    Parameters
    ----------
    t_s : ndarray, shape (T,)
        Sample times [s].
    target_rpm : ndarray, shape (T, 4)
        Wheel targets [rpm] (e.g. :func:`mecanum_hil.identify.regimes.wheel_targets`).
    wheels : sequence of int, optional
        Wheels to split (default: all four).

    Returns
    -------
    list of Step
        By wheel, then in time.
    """
    t = np.asarray(t_s, dtype=float)
    tg = np.asarray(target_rpm, dtype=float).reshape(len(t), -1)
    out: list[Step] = []
    for w in (range(tg.shape[1]) if wheels is None else wheels):
        u = tg[:, w]
        big = max(JUMP_MIN_RPM, JUMP_SHARE * float(np.max(np.abs(u)))) if u.size else 1.0
        starts = list(np.flatnonzero(np.abs(np.diff(u)) > big) + 1)
        if u.size and abs(u[0]) > big:
            starts.insert(0, 0)
        for k, j in enumerate(starts):
            stop = starts[k + 1] if k + 1 < len(starts) else len(t)
            if stop - j < 2:
                continue
            out.append(Step(w, k, int(j), int(stop), float(t[j]), float(t[stop - 1]),
                            float(u[j - 1]) if j else 0.0, float(u[j])))
    # renumber per wheel after dropping too-short steps
    renum, count = [], {}
    for s in out:
        i = count.get(s.wheel, 0)
        count[s.wheel] = i + 1
        renum.append(Step(s.wheel, i, s.start, s.stop, s.t_start_s, s.t_end_s, s.before_rpm,
                          s.target_rpm))
    return renum


def level(y: np.ndarray, start: int, stop: int) -> float:
    """Mean of the finite values of ``y`` over the last :data:`LEVEL_SHARE` of rows
    ``start:stop`` (at least one row) [same unit as ``y``]; NaN without any."""
    n = stop - start
    first = stop - max(math.ceil(LEVEL_SHARE * n), 1)
    seg = np.asarray(y[first:stop], dtype=float)
    seg = seg[np.isfinite(seg)]
    return float(seg.mean()) if seg.size else math.nan


def time_to_half(t_s: np.ndarray, y: np.ndarray, start: int, stop: int, before: float,
                 after: float) -> float:
    """Time from ``t_s[start]`` to the first crossing of ``(before + after) / 2`` by ``y`` in
    rows ``start:stop``, linearly interpolated [s]; NaN when it is not crossed."""
    t = np.asarray(t_s, dtype=float)[start:stop]
    v = np.asarray(y, dtype=float)[start:stop]
    ok = np.isfinite(v)
    t, v = t[ok], v[ok]
    if not v.size or not (math.isfinite(before) and math.isfinite(after)) or after == before:
        return math.nan
    half = 0.5 * (before + after)
    sgn = 1.0 if after > before else -1.0
    hit = np.flatnonzero(sgn * (v - half) >= 0)
    if not hit.size:
        return math.nan
    j = int(hit[0])
    t0 = float(np.asarray(t_s, dtype=float)[start])
    if j == 0:
        return float(t[0] - t0)
    f = (half - v[j - 1]) / (v[j] - v[j - 1])
    return float(t[j - 1] + f * (t[j] - t[j - 1]) - t0)


def step_figures(t_s: np.ndarray, y: np.ndarray, steps: Sequence[Step],
                 noise_rpm: float = 0.0) -> list[StepFigures]:
    """:class:`StepFigures` of one wheel's series ``y`` [rpm] on its ``steps`` (one wheel's, in
    time order, as :func:`split_steps` gives them).

    ``noise_rpm`` sets the smallest move for which a time to 50 % is computed (four noise
    levels, or :data:`MIN_MOVE` of the target change, the larger).
    """
    y = np.asarray(y, dtype=float)
    out: list[StepFigures] = []
    prev_level: float | None = None
    for s in steps:
        lv = level(y, s.start, s.stop)
        if prev_level is None or s.index == 0:
            head = y[max(s.start - 2, 0):s.start + 1]
            head = head[np.isfinite(head)]
            before = float(head.mean()) if head.size else 0.0
            if s.start == 0:
                before = float(y[0]) if np.isfinite(y[0]) else 0.0
        else:
            before = prev_level
        move = abs(lv - before)
        need = max(MIN_MOVE * abs(s.target_rpm - s.before_rpm), 4.0 * noise_rpm)
        t50 = (time_to_half(t_s, y, s.start, s.stop, before, lv)
               if math.isfinite(move) and move >= need else math.nan)
        out.append(StepFigures(t50, lv))
        prev_level = lv
    return out


@dataclass(frozen=True)
class StepRow:
    """One step of one wheel with the figures of every series.

    Attributes
    ----------
    step : Step
    figures : dict of str to StepFigures
        Series label (``measured`` and each model's) -> its figures.
    """

    step: Step
    figures: dict[str, StepFigures]


def step_table(t_s: np.ndarray, target_rpm: np.ndarray, series: Mapping[str, np.ndarray],
               noise_rpm: float = 0.0) -> list[StepRow]:
    """Per step and per wheel, the figures of every series.

    Parameters
    ----------
    t_s : ndarray, shape (T,)
    target_rpm : ndarray, shape (T, 4)
        Wheel targets [rpm].
    series : mapping of str to ndarray (T, 4)
        Label -> wheel speeds [rpm]; the first is the reference (``measured``): wheels it
        does not measure (all NaN) are left out, and the others are compared at its samples.
    noise_rpm : float
        Wheel noise level [rpm] (sets the smallest move with a time to 50 %).

    Returns
    -------
    list of StepRow
        By wheel, then in time.
    """
    labels = list(series)
    ref = np.asarray(series[labels[0]], dtype=float)
    wheels = [w for w in range(ref.shape[1]) if np.isfinite(ref[:, w]).any()]
    steps = split_steps(t_s, target_rpm, wheels)
    rows: list[StepRow] = []
    for w in wheels:
        mine = [s for s in steps if s.wheel == w]
        mask = np.isfinite(ref[:, w])
        figs = {lab: step_figures(t_s, np.where(mask, np.asarray(series[lab], float)[:, w],
                                                np.nan), mine, noise_rpm)
                for lab in labels}
        rows += [StepRow(s, {lab: figs[lab][k] for lab in labels}) for k, s in enumerate(mine)]
    return rows


def step_errors(rows: Sequence[StepRow], model: str, reference: str = "measured"
                ) -> tuple[np.ndarray, np.ndarray]:
    """Model minus reference, per row: time to 50 % [s] and level [rpm] (NaN where either is
    undefined)."""
    dt = np.array([r.figures[model].t50_s - r.figures[reference].t50_s for r in rows])
    dl = np.array([r.figures[model].level_rpm - r.figures[reference].level_rpm for r in rows])
    return dt, dl
