"""``measure-video`` as a library: a video of wheel markers in, a recording of wheel speeds out.

One pass over the video: each frame is decoded (in a helper thread, so decoding and analysis
overlap on two cores) and searched for marker candidates in each wheel's region. After the pass
the marker of each wheel is chosen (:func:`~mecanum_hil.vision.geometry.select_track`), its angle
taken on the path mapped to a circle, unwrapped and differentiated
(:func:`~mecanum_hil.vision.speed.wheel_speed_rpm`).
"""

from __future__ import annotations

import math
import queue
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..errors import VideoError
from ..io.recording import Recording, empty_like_times
from .detect import BlobDetector, MarkerSpec
from .geometry import select_track
from .speed import wheel_speed_rpm
from .video import FrameTiming, frame_times, iter_frames, open_video

#: Default regression window of the speed estimate [s] (see docs/vision.md).
DEFAULT_WINDOW_S = 0.1
#: Default smallest share of frames with the marker found for a trustworthy result.
DEFAULT_MIN_FOUND = 0.5
#: RMS distance of the detections from the fitted path above which a warning is given [px].
PATH_RESIDUAL_WARN_PX = 0.5
#: Share of a turn below which the path's shape (circle or ellipse) is uncertain (a warning).
SHORT_ARC = 0.5
#: Frames after which (and after twice, four times as many ...) the marker's path is looked
#: for, to measure only blobs near it from then on.
FOCUS_AFTER_FRAMES = 60


@dataclass(frozen=True)
class MeasureOptions:
    """How to measure.

    Attributes
    ----------
    rois : tuple of (wheel, (x, y, w, h) or None)
        One entry per measured wheel; ``None``: the whole frame.
    marker : MarkerSpec
    invert : bool
        Clockwise in the image counts positive.
    fps : float or None
        Frame rate overriding the video's timestamps [1/s].
    window_s : float
        Speed regression window [s].
    min_found : float
        Smallest share of frames with the marker (0..1); below it the result is refused.
    seed : int
        Seed of the robust path search (results do not depend on it in practice).
    """

    rois: tuple[tuple[int, tuple[int, int, int, int] | None], ...] = ((1, None),)
    marker: MarkerSpec = field(default_factory=MarkerSpec)
    invert: bool = False
    fps: float | None = None
    window_s: float = DEFAULT_WINDOW_S
    min_found: float = DEFAULT_MIN_FOUND
    seed: int = 0

    def __post_init__(self) -> None:
        wheels = [w for w, _ in self.rois]
        if not wheels or len(set(wheels)) != len(wheels):
            raise VideoError("give each wheel at most one --roi")
        if not 0.0 <= self.min_found <= 1.0:
            raise VideoError(f"--min-found must be within 0..1, got {self.min_found}")
        if not self.window_s > 0:
            raise VideoError(f"--window must be > 0 s, got {self.window_s}")


@dataclass(frozen=True)
class VideoMeasurement:
    """The result of :func:`measure_video`.

    Attributes
    ----------
    recording : Recording
        ``t_s`` from the frames, the measured wheels' columns filled, the rest empty; extra
        columns ``wheelN_turns`` (unwrapped angle [turns]).
    summary : dict
        Machine-readable summary (keys in docs/vision.md).
    warnings : tuple of str
    """

    recording: Recording
    summary: dict[str, Any]
    warnings: tuple[str, ...]


def _decode_ahead(cap, out: queue.Queue, stop: threading.Event) -> None:
    try:
        for item in iter_frames(cap):
            while not stop.is_set():
                try:
                    out.put(item, timeout=0.1)
                    break
                except queue.Full:
                    continue
            if stop.is_set():
                return
        out.put(None)
    except BaseException as err:  # handed to the consumer, which re-raises it
        out.put(err)


def scan_video(path: str | Path, detectors_for: Callable[[tuple[int, int]], Sequence],
               progress: Callable[[int, int], None] | None = None):
    """Decode every frame once and run the detectors on it.

    Returns ``(info, stamps [s], per-detector lists of per-frame results, detectors)``.
    """
    cap, info = open_video(path)
    detectors = detectors_for((info.width_px, info.height_px))
    results: list[list] = [[] for _ in detectors]
    stamps: list[float] = []
    q: queue.Queue = queue.Queue(maxsize=8)
    stop = threading.Event()
    next_focus = FOCUS_AFTER_FRAMES
    worker = threading.Thread(target=_decode_ahead, args=(cap, q, stop), daemon=True)
    worker.start()
    try:
        while True:
            item = q.get()
            if item is None:
                break
            if isinstance(item, BaseException):
                raise item
            _, t, frame = item
            if frame.shape[1] != info.width_px or frame.shape[0] != info.height_px:
                raise VideoError(f"{path}: frame {len(stamps)} has another size than the first")
            stamps.append(t)
            for k, det in enumerate(detectors):
                results[k].append(det(frame))
            if len(stamps) == next_focus:
                next_focus *= 2
                for k, det in enumerate(detectors):
                    if isinstance(det, BlobDetector) and det.path is None:
                        _focus(det, results[k])
            if progress is not None:
                progress(len(stamps), info.frame_count)
    finally:
        stop.set()
        worker.join(timeout=5.0)
        cap.release()
    return info, np.array(stamps, dtype=float), results, detectors


def _focus(det: BlobDetector, cands: list[np.ndarray]) -> None:
    """Find the marker's path in the frames so far; if it is clear, focus the detector on it."""
    n = len(cands)
    frame_idx = np.concatenate([np.full(len(c), i) for i, c in enumerate(cands)]).astype(int)
    allc = np.concatenate(cands)
    try:
        track = select_track(frame_idx, allc[:, :2], allc[:, 2], n, det.size_px,
                             np.random.default_rng(1), hypotheses=200)
    except VideoError:
        return
    if track.found.mean() >= 0.9 and track.coverage >= 0.25:
        det.focus(track.path)


def _wheel_angles(cands: list[np.ndarray], n: int, detector: BlobDetector, seed: int,
                  source: str):
    frame_idx = np.concatenate([np.full(len(c), i) for i, c in enumerate(cands)]).astype(int)
    allc = np.concatenate(cands) if cands else np.empty((0, 4))
    track = select_track(frame_idx, allc[:, :2], allc[:, 2], n, detector.size_px,
                         np.random.default_rng(seed), source=source, initial=detector.path)
    angle = np.full(n, np.nan)
    _, ang = track.path.unit(track.xy_px[track.found])
    angle[track.found] = ang
    return track, angle


def measure_video(path: str | Path, options: MeasureOptions | None = None,
                  progress: Callable[[int, int], None] | None = None) -> VideoMeasurement:
    """Measure wheel speeds from a video of wheel markers.

    Parameters
    ----------
    path : str or Path
        Any video OpenCV decodes.
    options : MeasureOptions, optional
    progress : callable, optional
        ``progress(frames done, frames declared or 0)``.

    Raises
    ------
    VideoError
        Unreadable video, no frame rate, no marker, marker in too few frames, aliasing.
    """
    opts = options or MeasureOptions()
    src = str(path)
    def make(size):
        if opts.marker.kind == "aruco":
            from .aruco import ArucoDetector

            return [ArucoDetector(roi, size) for _, roi in opts.rois]
        return [BlobDetector(opts.marker, roi, size) for _, roi in opts.rois]

    info, stamps, per_wheel, detectors = scan_video(path, make, progress)
    n = stamps.size
    if n < 3:
        raise VideoError(f"{src}: only {n} frame(s) could be decoded (empty or corrupt video)")
    warnings: list[str] = []
    if info.frame_count and n < info.frame_count - 1:
        warnings.append(f"the video ends after {n} of the {info.frame_count} frames its header "
                        "declares (truncated?); measured what could be decoded")
    timing = frame_times(stamps, info.fps_nominal, opts.fps, src)
    if timing.variable:
        warnings.append("variable frame rate: speeds use the frame timestamps")
    rec = empty_like_times(timing.t_s)
    wheel_rpm = rec.wheel_rpm.copy()
    extra: dict[str, list[str]] = {}
    wheels_summary = []
    for (wheel, roi), cands, det in zip(opts.rois, per_wheel, detectors, strict=True):
        where = f"{src}, wheel {wheel}"
        if opts.marker.kind == "aruco":
            from .aruco import aruco_angles

            angle, geom = aruco_angles(cands, where)
        else:
            track, angle = _wheel_angles(cands, n, det, opts.seed, where)
            geom = {"path": track.shape, "centre_px": [round(track.path.cx_px, 2),
                                                       round(track.path.cy_px, 2)],
                    "axes_px": [round(track.path.a_px, 2), round(track.path.b_px, 2)],
                    "axis_angle_deg": round(track.path.angle_deg, 2),
                    "view_tilt_deg": round(track.path.tilt_deg, 1),
                    "path_coverage": round(track.coverage, 3),
                    "path_residual_px": round(track.residual_px, 3)}
            if track.residual_px > PATH_RESIDUAL_WARN_PX:
                warnings.append(
                    f"wheel {wheel}: the marker's detections lie {track.residual_px:.1f} px (RMS) "
                    f"off the fitted {track.shape} (glare, a moving camera, strong perspective?): "
                    "speeds may be off by several percent")
            if track.coverage < SHORT_ARC:
                warnings.append(
                    f"wheel {wheel}: the marker was seen on only {100 * track.coverage:.0f}% of "
                    f"a turn, too little to tell its path's shape (taken as: {track.shape}); if "
                    "the camera looks at the wheel obliquely, speeds may be off by up to "
                    "1 - cos(view angle); film at least half a turn")
        found = np.isfinite(angle)
        share = float(found.mean())
        if share < opts.min_found:
            raise VideoError(f"{where}: marker found in only {100 * share:.0f}% of the frames "
                             f"(need {100 * opts.min_found:.0f}%, see --min-found)")
        rpm, turns, outliers = wheel_speed_rpm(timing.t_s, angle, opts.window_s, opts.invert)
        wheel_rpm[:, wheel - 1] = rpm
        extra[f"wheel{wheel}_turns"] = ["" if not math.isfinite(v) else f"{v:.6f}" for v in turns]
        speeds = rpm[np.isfinite(rpm)]
        wheels_summary.append({
            "wheel": wheel, "roi": list(roi) if roi is not None else None,
            "found_fraction": round(share, 4), "frames_found": int(found.sum()),
            "outliers_dropped": outliers,
            "speed_samples": int(speeds.size),
            "mean_rpm": round(float(speeds.mean()), 3) if speeds.size else None,
            "max_abs_rpm": round(float(np.abs(speeds).max()), 3) if speeds.size else None,
            **geom})
    summary = {
        "video": src, "frames": n, "fps": round(timing.fps, 4),
        "fps_declared": None if math.isnan(info.fps_nominal) else info.fps_nominal,
        "duration_s": round(float(timing.t_s[-1]), 4), "timing": timing.source,
        "variable_frame_rate": timing.variable, "size_px": [info.width_px, info.height_px],
        "marker": opts.marker.kind, "method": _method(opts, timing),
        "wheels": wheels_summary, "offset_s": None, "warnings": warnings,
    }
    meta = {"source": "mecanum-hil measure-video", "tool_version": __version__,
            "source_video": src, "fps": summary["fps"], "timing": timing.source,
            "method": summary["method"], "offset_s": None,
            "wheels": wheels_summary, "marker": opts.marker.kind, "invert": opts.invert}
    rec = rec.with_values(wheel_rpm=wheel_rpm, extra=extra, metadata=meta)
    return VideoMeasurement(rec, summary, tuple(warnings))


def _method(opts: MeasureOptions, timing: FrameTiming) -> str:
    from .speed import half_window

    h = half_window(timing.fps, opts.window_s)
    marker = {"auto": "saturated-blob centroid, angle on the path mapped to a circle",
              "hsv": "HSV-blob centroid, angle on the path mapped to a circle",
              "aruco": "ArUco marker orientation with the view's distortion removed",
              }[opts.marker.kind]
    return (f"{marker}, unwrapped; speed = slope of a local quadratic regression over "
            f"{2 * h + 1} frames")


def align_with_recording(measurement: VideoMeasurement, rec: Recording, calibration=None,
                         robot=None) -> tuple[Recording, VideoMeasurement]:
    """Find the clock offset against a recording and merge the measurement into it.

    The offset comes from the first measured wheel (see :mod:`~mecanum_hil.vision.align`);
    every measured wheel is merged. Returns ``(merged recording, measurement with the offset in
    its summary and metadata)``.
    """
    from .align import estimate_offset, merge, reference_speed

    wheels = [w["wheel"] for w in measurement.summary["wheels"]]
    meas = measurement.recording
    ref, ref_name = reference_speed(rec, wheels[0], calibration, robot)
    al = estimate_offset(meas.t_s, meas.wheel_rpm[:, wheels[0] - 1], rec.t_s, ref)
    warnings = list(measurement.warnings)
    if al.correlation < 0:
        warnings.append(f"the video sees wheel {wheels[0]} turn against the {ref_name} "
                        f"(correlation {al.correlation:.2f}): film it from the other side or "
                        "pass --invert")
    if al.method != "cross-correlation":
        warnings.append(f"the speeds correlate weakly ({al.correlation:.2f}): offset from the "
                        "motion onsets only")
    info = {**al.as_dict(), "reference": ref_name}
    merged = rec
    for w in wheels:
        merged = merge(merged, meas.t_s, meas.wheel_rpm[:, w - 1], w, al.offset_s,
                       {"video_alignment": info, "video_measurement": dict(meas.metadata)})
    summary = {**measurement.summary, "offset_s": info["offset_s"], "alignment": info,
               "warnings": warnings}
    new_meas = VideoMeasurement(
        meas.with_values(metadata={**dict(meas.metadata), "offset_s": info["offset_s"],
                                   "alignment": info}), summary, tuple(warnings))
    return merged, new_meas
