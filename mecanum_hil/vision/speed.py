"""From marker angles to wheel speed: unwrapping, aliasing check, local regression (pure).

Speed is the slope of a local quadratic regression of the unwrapped angle on time over a window
of ``2 h + 1`` frames centred on each frame (a Savitzky-Golay differentiator when frames are
evenly spaced; uneven frame times are used as they are). A quadratic fit keeps constant
acceleration unbiased, also one-sided at the ends of a run. The noise of the slope falls as
``h^-1.5`` while a speed step is spread over ``h`` frames each side; the default window is chosen
so a step's onset stays within one frame (see docs/vision.md).
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import VideoError

#: Largest apparent motion between frames that is trusted [turns]; beyond it the marker may
#: have moved the other way round (aliasing, the sampling limit is half a turn per frame).
ALIAS_STEP_TURNS = 0.4
#: Longest run of missing frames that a track is unwrapped across [frames].
MAX_GAP_FRAMES = 2


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
    idx = lo[:, None] + np.arange(2 * h + 1)[None, :]
    inside = idx <= last[:, None]
    idx_c = np.clip(idx, 0, n - 1)
    use = inside & (run[idx_c] == run[:, None]) & valid[:, None]
    scale = float(np.median(np.diff(t_s))) if n > 1 else 1.0
    dt = np.where(use, (t_s[idx_c] - t_s[:, None]) / scale, 0.0)
    dy = np.where(use, y[idx_c] - np.where(np.isfinite(y), y, 0.0)[:, None], 0.0)
    w = use.astype(float)
    S = [np.sum(w * dt ** k, axis=1) for k in range(5)]
    T = [np.sum(w * dt ** k * dy, axis=1) for k in range(3)]
    M = np.stack([np.stack([S[0], S[1], S[2]], -1), np.stack([S[1], S[2], S[3]], -1),
                  np.stack([S[2], S[3], S[4]], -1)], -2)
    rhs = np.stack(T, -1)
    count = w.sum(axis=1)
    det = np.linalg.det(M)
    good = (count >= 3) & (np.abs(det) > 1e-12)
    if good.any():
        sol = np.linalg.solve(M[good], rhs[good][..., None])[..., 0]
        out[good] = sol[:, 1] / scale
    pair = (count == 2) & ~good
    if pair.any():
        out[pair] = T[1][pair] / np.where(S[2][pair] > 0, S[2][pair], np.nan) / scale
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
