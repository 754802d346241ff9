"""A measured pose track (camera, motion capture) put onto a recording's times (pure).

A track is ``(t_s, pose)`` with ``pose`` of shape (N, 3): ``(X [m], Y [m], phi [deg])``, NaN
where nothing was measured. Its clock is its own: ``recording time = track time + offset_s``.
Resampling is linear between two neighbouring samples that are both measured and no further
apart than ``max_gap_s``; nothing is extrapolated (outside the track, or across a gap, the
result is empty).
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import RecordingError
from .recording import Recording

#: Motion that counts as the robot's onset: displacement plus this radius times the turn [m].
ONSET_TURN_RADIUS_M = 0.3
#: Default onset threshold [m] (see :func:`motion_onset`).
ONSET_THRESHOLD_M = 0.01


def unwrap_deg(phi_deg: np.ndarray) -> np.ndarray:
    """Heading made continuous over the measured samples (NaN kept) [deg]."""
    out = np.array(phi_deg, dtype=float)
    f = np.isfinite(out)
    if f.any():
        out[f] = np.degrees(np.unwrap(np.radians(out[f])))
    return out


def resample_pose(track_t_s: np.ndarray, track_pose: np.ndarray, query_t_s: np.ndarray,
                  max_gap_s: float | None = None) -> np.ndarray:
    """The track at query times (same clock), linear between neighbouring measured samples.

    Parameters
    ----------
    track_t_s : ndarray, shape (N,)
        Increasing sample times [s].
    track_pose : ndarray, shape (N, 3)
        ``(X [m], Y [m], phi [deg])``, NaN where not measured.
    query_t_s : ndarray, shape (M,)
    max_gap_s : float, optional
        Largest spacing of two samples interpolated between [s]; default 1.5 x the median
        spacing (so one missing sample is a gap).

    Returns
    -------
    ndarray, shape (M, 3)
        NaN outside the track, next to unmeasured samples and across gaps.
    """
    t = np.asarray(track_t_s, dtype=float)
    p = np.asarray(track_pose, dtype=float).copy()
    q = np.asarray(query_t_s, dtype=float)
    out = np.full((q.size, 3), np.nan)
    if t.size < 2:
        return out
    p[:, 2] = unwrap_deg(p[:, 2])
    gap = 1.5 * float(np.median(np.diff(t))) if max_gap_s is None else float(max_gap_s)
    ok = np.isfinite(p).all(axis=1)
    i = np.searchsorted(t, q, side="right") - 1
    inside = (q >= t[0]) & (q <= t[-1])
    i = np.clip(i, 0, t.size - 2)
    exact = inside & (q == t[np.clip(i, 0, t.size - 1)])
    j = i + 1
    span = t[j] - t[i]
    usable = inside & ok[i] & ok[j] & (span <= gap + 1e-12)
    w = np.where(usable, (q - t[i]) / np.where(span > 0, span, 1.0), 0.0)
    out[usable] = p[i[usable]] + w[usable, None] * (p[j[usable]] - p[i[usable]])
    # a query exactly on a measured sample takes it, whatever its neighbours
    hit = exact & ok[i]
    out[hit] = p[i[hit]]
    last = inside & (q == t[-1]) & ok[-1]
    out[last] = p[-1]
    return out


def motion_measure(pose: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """How far from ``rest`` each pose is: displacement [m] plus
    :data:`ONSET_TURN_RADIUS_M` times the turn [rad]."""
    p = np.asarray(pose, dtype=float)
    d = np.hypot(p[:, 0] - rest[0], p[:, 1] - rest[1])
    return d + ONSET_TURN_RADIUS_M * np.abs(np.radians(p[:, 2] - rest[2]))


def motion_onset(t_s: np.ndarray, pose: np.ndarray,
                 threshold_m: float = ONSET_THRESHOLD_M) -> float | None:
    """Time [s] the pose first moves ``threshold_m`` (see :func:`motion_measure`) from where it
    rests at the start (the mean of its first five measured samples), linear between samples;
    ``None`` when it never does, or moves from its first samples on."""
    t = np.asarray(t_s, dtype=float)
    p = np.asarray(pose, dtype=float).copy()
    p[:, 2] = unwrap_deg(p[:, 2])
    f = np.flatnonzero(np.isfinite(p).all(axis=1))
    if f.size < 6:
        return None
    rest = p[f[:5]].mean(axis=0)
    m = motion_measure(p[f], rest)
    above = np.flatnonzero(m > threshold_m)
    if above.size == 0 or above[0] < 5:
        return None
    k = above[0]
    a, b = m[k - 1], m[k]
    ta, tb = t[f[k - 1]], t[f[k]]
    return float(ta + (threshold_m - a) / (b - a) * (tb - ta))


def onset_offset(track_t_s: np.ndarray, track_pose: np.ndarray, model_t_s: np.ndarray,
                 model_pose: np.ndarray, threshold_m: float = ONSET_THRESHOLD_M,
                 source: str = "track") -> float:
    """Clock offset ``recording time - track time`` [s] that puts the track's motion onset on
    the model's (the model's prediction for the recording's commands).

    Raises
    ------
    RecordingError
        The track or the model shows no onset (the robot moves from the track's start, or never).
    """
    t_track = motion_onset(track_t_s, track_pose, threshold_m)
    if t_track is None:
        raise RecordingError(f"{source}: no motion onset (the robot must rest at the start and "
                             f"then move {100 * threshold_m:g} cm); give the start time instead "
                             "of auto")
    t_model = motion_onset(model_t_s, model_pose, threshold_m)
    if t_model is None:
        raise RecordingError(f"{source}: the recording's commands never move the robot "
                             f"{100 * threshold_m:g} cm: the start time cannot be found, give it")
    return float(t_model - t_track)


def fill_pose(rec: Recording, track_t_s: np.ndarray, track_pose: np.ndarray, offset_s: float,
              metadata: dict | None = None, max_gap_s: float | None = None, *,
              track: str = "the track", recording: str = "the recording",
              offset_option: str = "the start offset") -> Recording:
    """The recording with its pose columns replaced by the track's at ``t_s - offset_s``
    (empty where the track has no value; heading continuous).

    Raises
    ------
    RecordingError
        When not one row would get a pose: the track, placed at ``offset_s``, does not
        overlap the recording, or the robot was not measured at any of its times. The message
        names ``track``, ``recording`` and the option that set the offset (``offset_option``).
    """
    if not math.isfinite(offset_s):
        raise RecordingError(f"the start offset must be finite, got {offset_s}")
    pose = resample_pose(track_t_s, track_pose, rec.t_s - offset_s, max_gap_s)
    if not np.isfinite(pose).all(axis=1).any():
        raise RecordingError(_no_pose_rows(rec, track_t_s, track_pose, offset_s, track,
                                           recording, offset_option))
    meta = dict(rec.metadata)
    meta.update(metadata or {})
    return rec.with_values(pose=pose, metadata=meta)


def _no_pose_rows(rec: Recording, track_t_s: np.ndarray, track_pose: np.ndarray,
                  offset_s: float, track: str, recording: str, offset_option: str) -> str:
    """Why no row of the recording got a pose: the track's times (from ``offset_s``) miss the
    recording's, or the robot was not measured at those times."""
    t = np.asarray(track_t_s, dtype=float)
    seen = np.isfinite(np.asarray(track_pose, dtype=float)).all(axis=1)
    v0, v1 = (offset_s + float(t.min()), offset_s + float(t.max())) if t.size else (math.nan,
                                                                                    math.nan)
    r0, r1 = (float(np.min(rec.t_s)), float(np.max(rec.t_s))) if len(rec) else (math.nan,
                                                                                math.nan)
    if not len(rec):
        return f"{recording}: the recording has no rows: no pose to fill"
    if not t.size or v1 < r0 or v0 > r1:
        return (f"{track} (recording time {v0:.3f} to {v1:.3f} s with its first sample at "
                f"{offset_s:g} s, {offset_option}) does not overlap the recording {recording} "
                f"({r0:.3f} to {r1:.3f} s): no pose to fill")
    return (f"{track} measured the robot at no time of a row of {recording} ({int(seen.sum())} "
            f"of {seen.size} samples measured, first sample at {offset_s:g} s, {offset_option}): "
            "no pose to fill")
