"""Align a video measurement with a recording made by ``record`` (the clocks differ) (pure).

The offset ``offset_s`` is such that ``recording time = video time + offset_s``. It is found by
the normalised cross-correlation of the measured wheel speed with the reference speed of the
same wheel (the model's prediction for the recording's commands, or the recording's own wheel
column when it has no commands), refined to a fraction of a frame by a parabola through the peak;
the motion onsets of both are compared as a check and are the fallback when the correlation is
weak (a single short step correlates well, a standstill does not at all).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import VideoError
from ..io.recording import WHEEL_COLUMNS, Recording

#: Correlation below which the cross-correlation offset is not trusted.
MIN_CORRELATION = 0.7


@dataclass(frozen=True)
class Alignment:
    """The clock offset between a video and a recording.

    Attributes
    ----------
    offset_s : float
        ``recording time = video time + offset_s`` [s].
    method : str
        ``"cross-correlation"`` or ``"motion onset"``.
    correlation : float
        Peak normalised correlation (negative: the video sees the wheel turn the other way).
    onset_offset_s : float or None
        Offset from the motion onsets alone [s].
    """

    offset_s: float
    method: str
    correlation: float
    onset_offset_s: float | None

    def as_dict(self) -> dict:
        """JSON-ready form."""
        return {"offset_s": round(self.offset_s, 5), "method": self.method,
                "correlation": round(self.correlation, 4),
                "onset_offset_s": None if self.onset_offset_s is None
                else round(self.onset_offset_s, 5)}


def _onset(t: np.ndarray, v: np.ndarray, threshold: float) -> float | None:
    moving = np.isfinite(v) & (np.abs(v) > threshold)
    return float(t[np.argmax(moving)]) if moving.any() else None


def estimate_offset(video_t_s: np.ndarray, video_rpm: np.ndarray, ref_t_s: np.ndarray,
                    ref_rpm: np.ndarray) -> Alignment:
    """Offset of a measured speed against a reference speed (see the module docstring).

    Raises
    ------
    VideoError
        Neither the correlation nor the motion onsets give an offset.
    """
    tv = np.asarray(video_t_s, float)
    mv = np.asarray(video_rpm, float)
    dt = float(np.median(np.diff(tv)))
    k = np.arange(math.floor((tv[-1] - tv[0]) / dt) + 1)
    grid_v = tv[0] + k * dt
    valid = np.isfinite(mv)
    m = np.interp(grid_v, tv[valid], mv[valid]) if valid.sum() >= 2 else np.full(k.size, np.nan)
    # Grid points next to a gap stay empty: the correlation uses measured values only.
    near = np.interp(grid_v, tv, valid.astype(float)) > 0.999
    m[~near] = np.nan
    j = np.arange(math.floor((ref_t_s[-1] - ref_t_s[0]) / dt) + 1)
    p = np.interp(ref_t_s[0] + j * dt, ref_t_s, ref_rpm)
    scale = max(float(np.nanmax(np.abs(m))) if np.isfinite(m).any() else 0.0,
                float(np.max(np.abs(p))))
    threshold = max(2.0, 0.1 * scale)
    t_on_v = _onset(grid_v, m, threshold)
    t_on_p = _onset(ref_t_s, np.asarray(ref_rpm, float), threshold)
    onset = None if t_on_v is None or t_on_p is None else t_on_p - t_on_v
    need = max(10, int(0.5 * min(np.isfinite(m).sum(), j.size)))
    lags = np.arange(-(k.size - 1), j.size)
    r = np.full(lags.size, np.nan)
    for n, lag in enumerate(lags):
        a0, a1 = max(0, -lag), min(k.size, j.size - lag)
        if a1 - a0 < need:
            continue
        a = m[a0:a1]
        b = p[a0 + lag:a1 + lag]
        ok = np.isfinite(a)
        if ok.sum() < need:
            continue
        a, b = a[ok] - a[ok].mean(), b[ok] - b[ok].mean()
        den = math.sqrt(float(a @ a) * float(b @ b))
        if den > 0:
            r[n] = float(a @ b) / den
    if np.isfinite(r).any():
        i = int(np.nanargmax(np.abs(r)))
        frac = 0.0
        if 0 < i < r.size - 1 and np.isfinite(r[i - 1:i + 2]).all():
            y0, y1, y2 = np.abs(r[i - 1:i + 2])
            den = y0 - 2 * y1 + y2
            frac = 0.5 * (y0 - y2) / den if den < 0 else 0.0
        offset = ref_t_s[0] - tv[0] + (lags[i] + frac) * dt
        if abs(r[i]) >= MIN_CORRELATION:
            return Alignment(float(offset), "cross-correlation", float(r[i]), onset)
    best_r = float(r[int(np.nanargmax(np.abs(r)))]) if np.isfinite(r).any() else 0.0
    if onset is not None:
        return Alignment(float(onset), "motion onset", best_r, onset)
    raise VideoError("cannot align the video with the recording: the speeds do not correlate "
                     f"(best {best_r:.2f}) and no motion onset is seen in both")


def reference_speed(rec: Recording, wheel: int, calibration=None, robot=None
                    ) -> tuple[np.ndarray, str]:
    """The wheel speed to align against: the model's for the commands, else the recording's."""
    if rec.has_commands and calibration is not None and robot is not None:
        from ..prediction import predict

        return predict(rec, calibration, robot).wheel_rpm[:, wheel - 1], "model prediction"
    col = rec.wheel_rpm[:, wheel - 1]
    if len(rec) >= 2 and np.isfinite(col).all():
        return col, f"recorded {WHEEL_COLUMNS[wheel - 1]}"
    raise VideoError("the recording has neither complete commands nor a complete "
                     f"{WHEEL_COLUMNS[wheel - 1]} column to align the video with")


def merge(rec: Recording, video_t_s: np.ndarray, video_rpm: np.ndarray, wheel: int,
          offset_s: float, metadata: dict) -> Recording:
    """The recording with the measured speed put on its time base.

    The measured speed is interpolated linearly at ``t_s - offset_s`` between two measured
    frames (empty outside the video and next to gaps). It fills the wheel's column when that is
    empty, else goes into an extra column ``wheelN_video_rpm``.
    """
    tq = rec.t_s - offset_s
    valid = np.isfinite(video_rpm)
    vals = np.full(len(rec), np.nan)
    if valid.sum() >= 2:
        vals = np.interp(tq, video_t_s[valid], video_rpm[valid])
        near = np.interp(tq, video_t_s, valid.astype(float)) > 0.999
        vals[~near | (tq < video_t_s[0]) | (tq > video_t_s[-1])] = np.nan
    meta = {**dict(rec.metadata), **metadata}
    if not np.isfinite(rec.wheel_rpm[:, wheel - 1]).any():
        w = rec.wheel_rpm.copy()
        w[:, wheel - 1] = vals
        return rec.with_values(wheel_rpm=w, metadata=meta)
    from ..io.recording import format_value

    extra = dict(rec.extra)
    extra[f"wheel{wheel}_video_rpm"] = [format_value(float(v)) for v in vals]
    return rec.with_values(extra=extra, metadata=meta)
