"""From marker angles to wheel speed: unwrapping, aliasing check, local regression (pure).

Speed is the slope of a local quadratic regression of the unwrapped angle on time over a window
of ``2 h + 1`` frames centred on each frame (a Savitzky-Golay differentiator when frames are
evenly spaced; uneven frame times are used as they are). A quadratic fit keeps constant
acceleration unbiased, also one-sided at the ends of a run. The noise of the slope falls as
``h^-1.5`` while a speed step is spread over ``h`` frames each side; the default window is chosen
so a step's onset stays within one frame (see docs/vision.md).

:func:`estimate_speed` is what ``measure-video`` uses: it bridges gaps (the marker hidden) from
the speed on both sides when the whole-turn count across them is unambiguous and reports them
otherwise, and refuses (or, given the expected speed range, resolves) motions beyond half a
turn per frame. :func:`wheel_speed_rpm` is the strict form: runs are never bridged and aliasing
is an error.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from ..errors import VideoError

#: Largest apparent motion between frames that is trusted [turns]; beyond it the marker may
#: have moved the other way round (aliasing, the sampling limit is half a turn per frame).
ALIAS_STEP_TURNS = 0.4
#: Longest run of missing frames that a track is unwrapped across [frames].
MAX_GAP_FRAMES = 2
#: Values (frames x window) of the regression computed at once by :func:`local_slope`.
SLOPE_CHUNK_VALUES = 1 << 20


def reject_outliers(angle_rad: np.ndarray) -> tuple[np.ndarray, int]:
    """Drop single-frame jumps (a reflection or another blob taken for the marker once).

    A frame is an outlier when the marker jumps more than a quarter turn into it and out of it
    again, while the motion on both sides of it (two frames each) is slow and consistent. A wheel
    genuinely turning fast shows large steps on both sides too, so it is left to the aliasing
    check. Returns the angles with outliers set to NaN, and their number.
    """
    a = np.asarray(angle_rad, dtype=float) / (2 * np.pi)
    n = a.size
    if n < 5:
        return np.asarray(angle_rad, dtype=float).copy(), 0

    def step(x, y):
        return np.abs((y - x + 0.5) % 1.0 - 0.5)

    i = np.arange(2, n - 2)
    before, into = step(a[i - 2], a[i - 1]), step(a[i - 1], a[i])
    out_of, after = step(a[i], a[i + 1]), step(a[i + 1], a[i + 2])
    across = step(a[i - 1], a[i + 1])
    bad = (into > 0.25) & (out_of > 0.25) & (before < 0.1) & (after < 0.1) & (across < 0.2)
    out = np.asarray(angle_rad, dtype=float).copy()
    out[i[bad]] = np.nan
    return out, int(bad.sum())


def half_window(fps: float, window_s: float) -> int:
    """Half-width ``h`` [frames] of a regression window of about ``window_s`` [s]."""
    return max(1, math.floor(window_s * fps / 2.0 + 0.5))


def unwrap_runs(angle_rad: np.ndarray, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unwrap angles into turns, run by run.

    A run is a stretch of found frames whose gaps are at most :data:`MAX_GAP_FRAMES` long and
    across which the marker moved plausibly little; the whole-turn count between runs is
    unknown, so each run is unwrapped on its own. Returns ``(turns, run id)``, NaN / -1 where the
    marker was not found.

    Raises
    ------
    VideoError
        The marker moves half a turn or more per frame (aliasing).
    """
    n = angle_rad.size
    found = np.isfinite(angle_rad)
    turns = np.full(n, np.nan)
    run = np.full(n, -1, dtype=int)
    idx = np.flatnonzero(found)
    if idx.size == 0:
        return turns, run
    a = angle_rad[idx] / (2 * np.pi)
    step = (np.diff(a) + 0.5) % 1.0 - 0.5
    gap = np.diff(idx)
    per_frame = step / gap
    cut = (gap > MAX_GAP_FRAMES + 1) | ((gap > 1) & (np.abs(per_frame) > 0.15))
    consecutive = (gap == 1)
    big = consecutive & (np.abs(step) > ALIAS_STEP_TURNS)
    flip = (consecutive[:-1] & consecutive[1:] & (np.abs(step[:-1]) > 0.25)
            & (np.abs(step[1:]) > 0.25) & (np.sign(step[:-1]) != np.sign(step[1:])))
    if big.any() or flip.any():
        k = int(np.argmax(big)) if big.any() else int(np.argmax(flip)) + 1
        dt = t_s[idx[k + 1]] - t_s[idx[k]]
        limit = 30.0 / dt if dt > 0 else math.nan
        raise VideoError(
            f"aliasing at t={t_s[idx[k]]:.3f} s: the marker moves about half a turn or more "
            f"between frames (the limit is {limit:.0f} rpm at this frame rate); the speed "
            "cannot be told from its folded image: film at a higher frame rate")
    run_of = np.concatenate([[0], np.cumsum(cut)])
    unwrapped = np.concatenate([[a[0]], a[0] + np.cumsum(step)])
    # Each run starts from its own wrapped angle (the turns lost in a long gap are unknown).
    for r in range(int(run_of[-1]) + 1):
        sel = run_of == r
        first = int(np.argmax(sel))
        unwrapped[sel] += a[first] - unwrapped[first]
    turns[idx] = unwrapped
    run[idx] = run_of
    return turns, run


def local_slope(t_s: np.ndarray, y: np.ndarray, run: np.ndarray, h: int) -> np.ndarray:
    """Slope ``dy/dt`` of a local quadratic regression over ``2h+1`` frames, within runs.

    Near the ends of a run the window slides inward to keep ``2h+1`` frames (the polynomial is
    evaluated off-centre, as Savitzky-Golay's ``interp`` mode does), so a constant acceleration
    stays unbiased everywhere. A run of two frames gets their difference quotient; frames
    without a value get NaN.
    """
    n = y.size
    out = np.full(n, np.nan)
    if n == 0:
        return out
    pos = np.arange(n)
    valid = run >= 0
    # First and last index of each frame's run (runs are contiguous stretches of indices).
    first = np.full(n, -1)
    last = np.full(n, -1)
    if valid.any():
        ids = np.unique(run[valid])
        lo_of = {int(r): int(np.flatnonzero(run == r)[0]) for r in ids}
        hi_of = {int(r): int(np.flatnonzero(run == r)[-1]) for r in ids}
        first[valid] = [lo_of[int(r)] for r in run[valid]]
        last[valid] = [hi_of[int(r)] for r in run[valid]]
    lo = np.maximum(pos - h, first)
    lo = np.maximum(np.minimum(lo, last - 2 * h), first)
    scale = float(np.median(np.diff(t_s))) if n > 1 else 1.0
    y0 = np.where(np.isfinite(y), y, 0.0)
    # Rows in chunks: the (frames x window) arrays of a long video with a wide --window would
    # take gigabytes at once.
    rows = max(1, SLOPE_CHUNK_VALUES // (2 * h + 1))
    for c0 in range(0, n, rows):
        sl = slice(c0, min(n, c0 + rows))
        idx = lo[sl, None] + np.arange(2 * h + 1)[None, :]
        inside = idx <= last[sl, None]
        idx_c = np.clip(idx, 0, n - 1)
        use = inside & (run[idx_c] == run[sl, None]) & valid[sl, None]
        dt = np.where(use, (t_s[idx_c] - t_s[sl, None]) / scale, 0.0)
        dy = np.where(use, y[idx_c] - y0[sl, None], 0.0)
        w = use.astype(float)
        S = [np.sum(w * dt ** k, axis=1) for k in range(5)]
        T = [np.sum(w * dt ** k * dy, axis=1) for k in range(3)]
        M = np.stack([np.stack([S[0], S[1], S[2]], -1), np.stack([S[1], S[2], S[3]], -1),
                      np.stack([S[2], S[3], S[4]], -1)], -2)
        rhs = np.stack(T, -1)
        count = w.sum(axis=1)
        det = np.linalg.det(M)
        good = (count >= 3) & (np.abs(det) > 1e-12)
        part = out[sl]
        if good.any():
            sol = np.linalg.solve(M[good], rhs[good][..., None])[..., 0]
            part[good] = sol[:, 1] / scale
        pair = (count == 2) & ~good
        if pair.any():
            part[pair] = T[1][pair] / np.where(S[2][pair] > 0, S[2][pair], np.nan) / scale
    out[~valid] = np.nan
    return out


def wheel_speed_rpm(t_s: np.ndarray, angle_rad: np.ndarray, window_s: float,
                    invert: bool = False) -> tuple[np.ndarray, np.ndarray, int]:
    """Wheel speed [rpm] (CCW in the image positive), unwrapped angle [turns] per frame, and the
    number of single-frame outliers dropped (:func:`reject_outliers`).

    Parameters
    ----------
    t_s : ndarray, shape (N,)
        Frame times [s].
    angle_rad : ndarray, shape (N,)
        Marker angle, CCW positive, NaN where not found [rad].
    window_s : float
        Regression window [s] (at least 3 frames).
    invert : bool
        Count clockwise as positive.
    """
    t = np.asarray(t_s, dtype=float)
    a = np.asarray(angle_rad, dtype=float)
    if invert:
        a = -a
    a, outliers = reject_outliers(a)
    turns, run = unwrap_runs(a, t)
    fps = (t.size - 1) / (t[-1] - t[0]) if t.size > 1 and t[-1] > t[0] else 1.0
    return 60.0 * local_slope(t, turns, run, half_window(fps, window_s)), turns, outliers


#: A gap is bridged only when the motion predicted across it, plus its uncertainty, stays below
#: one turn (a whole turn could otherwise hide in it) and the nearest whole-turn count is this
#: far clear of the next one [turns].
BRIDGE_MARGIN_TURNS = 0.4
#: Apparent motion between frames from which a stretch of frames counts as fast [turns]; a fast
#: stretch holding an ambiguous step is refused as a whole.
FAST_STEP_TURNS = 0.25
#: Tolerance of an expected speed range, per frame [turns]: noise at rest must not make a wheel
#: expected to turn forwards appear to turn almost a whole turn.
RANGE_TOLERANCE_TURNS = 0.08


@dataclass(frozen=True)
class Gap:
    """A stretch of frames without the marker.

    Attributes
    ----------
    start_s, end_s : float
        Times of the first and last frame of the gap [s].
    frames : int
    bridged : bool
        Whether the angle was unwrapped across it (the whole-turn count is unambiguous).
    turns : float or None
        Motion across the gap when bridged [turns].
    reason : str
        Why it was not bridged (empty when bridged).
    """

    start_s: float
    end_s: float
    frames: int
    bridged: bool
    turns: float | None
    reason: str = ""

    def as_dict(self) -> dict:
        """JSON-ready form."""
        return {"start_s": round(self.start_s, 4), "end_s": round(self.end_s, 4),
                "frames": self.frames, "bridged": self.bridged,
                "turns": None if self.turns is None else round(self.turns, 3),
                "reason": self.reason}


@dataclass(frozen=True)
class SpeedEstimate:
    """What :func:`estimate_speed` found.

    Attributes
    ----------
    rpm : ndarray, shape (N,)
        Speed [rpm]; NaN where the marker was hidden or the speed cannot be resolved.
    turns : ndarray, shape (N,)
        Unwrapped angle [turns]; continuous across bridged gaps, NaN where unknown.
    outliers : int
        Single-frame outliers dropped (:func:`reject_outliers`).
    gaps : tuple of Gap
    aliased : ndarray of bool, shape (N,)
        Frames whose speed was refused as ambiguous (aliasing).
    """

    rpm: np.ndarray
    turns: np.ndarray
    outliers: int
    gaps: tuple[Gap, ...]
    aliased: np.ndarray

    @property
    def aliasing(self) -> bool:
        """Whether any frame was refused for aliasing."""
        return bool(self.aliased.any())


def _resolve_steps(step: np.ndarray, dt: np.ndarray, expected_rpm) -> np.ndarray:
    """Whole-turn-resolved steps between consecutive frames [turns]; NaN where ambiguous."""
    out = step.copy()
    if expected_rpm is None:
        bad = np.abs(step) > ALIAS_STEP_TURNS
        flip = np.zeros_like(bad)
        flip[1:] = ((np.abs(step[:-1]) > FAST_STEP_TURNS) & (np.abs(step[1:]) > FAST_STEP_TURNS)
                    & (np.sign(step[:-1]) != np.sign(step[1:])))
        bad |= flip
        # A fast stretch (steps over a quarter turn) that holds an ambiguous step is refused as
        # a whole: its other steps may be folded too.
        fast = np.abs(step) > FAST_STEP_TURNS
        edges = np.diff(np.concatenate([[0], fast.astype(int), [0]]))
        for s0, s1 in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True):
            if bad[s0:s1].any():
                bad[s0:s1] = True
        out[bad] = np.nan
        return out
    lo, hi = expected_rpm
    lo_t = lo / 60.0 * dt - RANGE_TOLERANCE_TURNS
    hi_t = hi / 60.0 * dt + RANGE_TOLERANCE_TURNS
    k_lo = np.ceil(np.where(np.isfinite(lo_t), lo_t - step, -np.inf))
    k_hi = np.floor(np.where(np.isfinite(hi_t), hi_t - step, np.inf))
    # Open-ended ranges (a sign only): the smallest motion in that direction.
    k_lo = np.where(np.isfinite(k_lo), k_lo, k_hi)
    k_hi = np.where(np.isfinite(k_hi), k_hi, k_lo)
    unique = (k_hi == k_lo) & np.isfinite(k_lo)
    out = np.where(unique, step + np.where(unique, k_lo, 0.0), np.nan)
    return out


def estimate_speed(t_s: np.ndarray, angle_rad: np.ndarray, window_s: float,
                   invert: bool = False,
                   expected_rpm: tuple[float, float] | None = None) -> SpeedEstimate:
    """Wheel speed from the marker angle per frame, across gaps and through aliasing.

    The found frames are cut into runs at gaps of more than :data:`MAX_GAP_FRAMES` missing
    frames and at ambiguous steps (aliasing). Within a run the angle is unwrapped and the speed
    is the local quadratic regression's slope (:func:`local_slope`). A gap between two runs of
    at least three frames is bridged from the speed on both sides: the motion across it is
    predicted as the mean of the two speeds times its length (exact for a constant
    acceleration), its uncertainty as half their difference times the length; the whole-turn
    count nearest the prediction is taken when that is unambiguous (see
    :data:`BRIDGE_MARGIN_TURNS`), else the gap is reported unbridged. No value is written for
    a frame without the marker.

    Parameters
    ----------
    t_s : ndarray, shape (N,)
        Frame times [s].
    angle_rad : ndarray, shape (N,)
        Marker angle, CCW positive, NaN where not found [rad].
    window_s : float
        Regression window [s].
    invert : bool
        Count clockwise as positive.
    expected_rpm : (low, high) or None
        The speed's expected range [rpm] (after ``invert``; an infinite bound for a sign
        only): resolves motions beyond half a turn per frame as long as one whole-turn count
        fits the range; without it such motions are refused (``aliased``).
    """
    t = np.asarray(t_s, dtype=float)
    a = np.asarray(angle_rad, dtype=float)
    if invert:
        a = -a
    # Also with an expected range: resolving a reflection's jump into the range would add a
    # whole turn (a spike of a turn per window); a real wheel never jumps out and back.
    a, outliers = reject_outliers(a)
    n = a.size
    rpm = np.full(n, np.nan)
    turns = np.full(n, np.nan)
    aliased = np.zeros(n, dtype=bool)
    idx = np.flatnonzero(np.isfinite(a))
    if idx.size == 0:
        return SpeedEstimate(rpm, turns, outliers, (), aliased)
    run, turns_run = _cut_into_runs(a, t, idx, expected_rpm, aliased)
    valid = run >= 0
    h = half_window((n - 1) / (t[-1] - t[0]) if n > 1 and t[-1] > t[0] else 1.0, window_s)
    slope = _edge_widened_slope(t, turns_run, np.where(valid, run, -1), h)
    rpm = 60.0 * slope
    ids = [int(r) for r in np.unique(run[valid])]
    turns_out, gaps = _bridge_runs(t, a, slope, run, ids, turns_run, aliased)
    gaps += _gaps_within_runs(t, run, ids, turns_run)
    gaps.sort(key=lambda g: g.start_s)
    return SpeedEstimate(rpm, turns_out, outliers, tuple(gaps), aliased)


def _cut_into_runs(a: np.ndarray, t: np.ndarray, idx: np.ndarray,
                   expected_rpm: tuple[float, float] | None, aliased: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Cut the found frames ``idx`` into runs; unwrap the angle within each.

    Returns each frame's run (-1: none) and its unwrapped angle [turns] (NaN outside a run).
    Frames on an ambiguous step are marked in ``aliased`` (in place).
    """
    n = a.size
    w = a[idx] / (2 * np.pi)
    raw = (np.diff(w) + 0.5) % 1.0 - 0.5
    gap = np.diff(idx)
    dt = np.diff(t[idx])
    consecutive = gap == 1
    step = raw.copy()
    resolved = _resolve_steps(raw[consecutive], dt[consecutive], expected_rpm)
    step[consecutive] = resolved
    ambiguous = consecutive & ~np.isfinite(step)
    for k in np.flatnonzero(ambiguous):
        aliased[idx[k]] = aliased[idx[k + 1]] = True
    # Short gaps with little motion stay inside a run; the others cut it.
    per_frame = raw / gap
    cut = ambiguous | (gap > MAX_GAP_FRAMES + 1) | ((gap > 1) & (np.abs(per_frame) > 0.15))
    if expected_rpm is not None:
        cut |= gap > 1
    run_of = np.concatenate([[0], np.cumsum(cut)])
    # Frames on an ambiguous step belong to no run: no speed is reported for them.
    keep = ~aliased[idx]
    unwrapped = np.concatenate([[w[0]], w[0] + np.cumsum(np.where(cut, 0.0, step))])
    run = np.full(n, -1, dtype=int)
    run[idx[keep]] = run_of[keep]
    turns_run = np.full(n, np.nan)
    turns_run[idx] = unwrapped
    turns_run[~(run >= 0)] = np.nan
    return run, turns_run


def _bridge_runs(t: np.ndarray, a: np.ndarray, slope: np.ndarray, run: np.ndarray,
                 ids: list[int], turns_run: np.ndarray, aliased: np.ndarray
                 ) -> tuple[np.ndarray, list[Gap]]:
    """Bridge the gaps between runs, in time order: the turns across each, where unambiguous.

    Returns the turns count of every frame [turns] and the gaps between runs.
    """
    gaps: list[Gap] = []
    turns_out = turns_run.copy()
    prev = None
    for r in ids:
        members = np.flatnonzero(run == r)
        if prev is not None:
            pm = np.flatnonzero(run == prev)
            i_end, i_start = int(pm[-1]), int(members[0])
            missing = i_start - i_end - 1
            turns_b = turns_run[members] - turns_run[i_start]
            hidden_alias = bool(aliased[i_end:i_start + 1].any())
            bridged, across, reason = _bridge(t, a, slope, pm, members, hidden_alias)
            if bridged:
                turns_out[members] = turns_out[i_end] + across + turns_b
            else:
                turns_out[members] = turns_b + w_of(a, i_start)
            if missing > 0 or not bridged:
                gaps.append(Gap(float(t[i_end + 1]), float(t[max(i_end + 1, i_start - 1)]),
                                missing, bridged, across if bridged else None, reason))
        prev = r
    return turns_out, gaps


def _gaps_within_runs(t: np.ndarray, run: np.ndarray, ids: list[int],
                      turns_run: np.ndarray) -> list[Gap]:
    """Short gaps inside runs (bridged by the run's own unwrapping)."""
    gaps: list[Gap] = []
    for r in ids:
        members = np.flatnonzero(run == r)
        for i0, i1 in itertools.pairwise(members):
            if i1 - i0 > 1:
                gaps.append(Gap(float(t[i0 + 1]), float(t[i1 - 1]), int(i1 - i0 - 1), True,
                                float(turns_run[i1] - turns_run[i0])))
    return gaps


def _edge_widened_slope(t: np.ndarray, y: np.ndarray, run: np.ndarray, h: int) -> np.ndarray:
    """:func:`local_slope`, with a window twice as wide within ``h`` frames of a run's ends.

    There the window cannot be centred and the quadratic's slope is extrapolated to its edge,
    which multiplies the angle noise several times; a wider window takes most of that back
    (with many gaps, as behind a fender, run ends are a large share of the frames).
    """
    slope = local_slope(t, y, run, h)
    wide = local_slope(t, y, run, 2 * h)
    n = y.size
    pos = np.arange(n)
    near_end = np.zeros(n, dtype=bool)
    for r in np.unique(run[run >= 0]):
        members = np.flatnonzero(run == r)
        near_end[members] = (pos[members] - members[0] < h) | (members[-1] - pos[members] < h)
    use = near_end & np.isfinite(wide)
    slope[use] = wide[use]
    return slope


def w_of(a: np.ndarray, i: int) -> float:
    """Wrapped angle of frame ``i`` [turns]."""
    return float(a[i] / (2 * np.pi))


def _end_acceleration(t: np.ndarray, slope: np.ndarray, frames: np.ndarray) -> float:
    """Mean acceleration over up to the last 8 frames of ``frames`` [turns/s^2] (NaN: unknown)."""
    k = frames[-min(frames.size, 8):]
    dt = float(t[k[-1]] - t[k[0]])
    return float(slope[k[-1]] - slope[k[0]]) / dt if dt > 0 else math.nan


def _bridge(t: np.ndarray, a: np.ndarray, slope: np.ndarray, before: np.ndarray,
            after: np.ndarray, aliased: bool) -> tuple[bool, float, str]:
    """Motion across the gap between two runs of frames [turns], if unambiguous.

    The motion is predicted from the speeds at both ends (``slope`` [turns/s]), the mean of the
    two times the gap's length (exact for a constant acceleration); its uncertainty is half
    their difference times the length (the most a speed changing monotonically between them
    can be off), a quarter of that when the accelerations measured at both ends agree with the
    one across the gap (a steady ramp). The whole-turn count nearest the prediction is taken
    when the next one lies clearly further (:data:`BRIDGE_MARGIN_TURNS`) and the motion stays
    below a turn.
    """
    if aliased:
        return False, math.nan, "aliasing"
    i_end, i_start = int(before[-1]), int(after[0])
    v_end, v_start = float(slope[i_end]), float(slope[i_start])
    if before.size < 3 or after.size < 3 or not (math.isfinite(v_end)
                                                 and math.isfinite(v_start)):
        return False, math.nan, "too few frames on one side to know the speed"
    span = float(t[i_start] - t[i_end])
    predicted = 0.5 * (v_end + v_start) * span
    uncertainty = 0.5 * abs(v_end - v_start) * span
    ramp = (v_start - v_end) / span
    acc_before = _end_acceleration(t, slope, before)
    acc_after = _end_acceleration(t, slope, after[::-1])
    tol = 0.25 * abs(ramp) + 0.02
    if abs(acc_before - ramp) <= tol and abs(-acc_after - ramp) <= tol:
        uncertainty *= 0.25
    w_end, w_start = w_of(a, i_end), w_of(a, i_start)
    seen = (w_start - w_end + 0.5) % 1.0 - 0.5
    across = seen + round(predicted - seen)
    miss = abs(across - predicted)
    if abs(across) + uncertainty >= 1.0:
        return False, math.nan, "long enough to hide a whole turn"
    if miss + uncertainty >= BRIDGE_MARGIN_TURNS:
        return False, math.nan, "the speeds either side do not fix the whole-turn count"
    return True, float(across), ""


def parse_speed_range(text: str) -> tuple[float, float]:
    """``"LO,HI"`` [rpm] as a range; an empty side is unbounded (``"0,"``: forwards only).

    Raises
    ------
    VideoError
        Not two numbers (or one and an empty side), or low not below high.
    """
    parts = text.split(",")
    try:
        if len(parts) != 2 or not (parts[0].strip() or parts[1].strip()):
            raise ValueError
        lo = float(parts[0]) if parts[0].strip() else -math.inf
        hi = float(parts[1]) if parts[1].strip() else math.inf
    except ValueError:
        raise VideoError(f"--speed-range '{text}': expected LO,HI in rpm, e.g. 0,1500, '0,' "
                         "(forwards only) or ',0'") from None
    if math.isnan(lo) or math.isnan(hi) or not lo < hi:
        raise VideoError(f"--speed-range '{text}': the low end must be below the high end")
    return lo, hi
