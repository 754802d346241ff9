"""``measure-video`` as a library: a video of wheel markers in, a recording of wheel speeds out.

One pass over the video: each frame is decoded (in runs of a few, looked at as soon as they are
decoded), the wheel's hub is located (:mod:`~mecanum_hil.vision.hub`: a camera that
shakes or drifts) and each wheel's region is searched for marker candidates. After the pass the
marker of each wheel is chosen over the whole video, relative to the hub
(:func:`~mecanum_hil.vision.geometry.select_track`), its angle taken on the path mapped to a
circle, unwrapped across gaps and differentiated (:func:`~mecanum_hil.vision.speed.estimate_speed`).
"""

from __future__ import annotations

import math
import queue
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from .._cores import SPARE_CORE
from .._cores import idle_cores as _idle_cores
from ..errors import VideoError
from ..io.recording import Recording, empty_like_times
from .detect import BlobDetector, MarkerSpec
from .geometry import refit_track, select_track
from .hub import STILL_CAMERA_PX, HubTracker, camera_offsets
from .speed import FAST_STEP_TURNS, estimate_speed
from .video import (
    MAX_FPS,  # noqa: F401  (re-exported: the bound was defined here first)
    MEETING_FRAMES,
    SEEK_BACK_FRAMES,
    FrameTiming,
    SegmentMismatchError,
    VideoInfo,
    check_fps,
    container_mismatch,
    decoded_ahead,
    decoded_in_segments,
    frame_times,
    iter_frames,
    keyframe_interval,
    open_video,
)

#: Default regression window of the speed estimate [s] (see docs/vision.md).
DEFAULT_WINDOW_S = 0.1
#: Default smallest share of frames with the marker found for a trustworthy result (a fender may
#: hide half of each turn, more while the wheel starts slowly behind it; the gaps are reported).
DEFAULT_MIN_FOUND = 0.3
#: Share of frames that must keep a speed when aliasing refuses some; below it the video is
#: refused as a whole (mostly beyond what the frame rate resolves).
ALIASED_MIN_SHARE = 0.5
#: RMS distance of the detections from the fitted path above which a warning is given [px].
PATH_RESIDUAL_WARN_PX = 0.5
#: Share of a turn below which the path's shape (circle or ellipse) is uncertain (a warning).
SHORT_ARC = 0.5
#: Frames after which (and after twice, four times as many ...) the marker's path is looked
#: for, to measure only blobs near it from then on.
FOCUS_AFTER_FRAMES = 60
#: Frames over which the camera is first watched; when the hub moved less than
#: :data:`~mecanum_hil.vision.hub.STILL_CAMERA_PX` (SD) over them, it is only checked every
#: STILL_CHECK_FRAMES frames from then on, until it has moved by STILL_MOVED_PX.
STILL_CHECK_AFTER = 60
STILL_CHECK_FRAMES = 10
STILL_MOVED_PX = 0.3
#: Frames decoded before they are looked at, as one run, where a hub is read in runs (see
#: scan_video).
SCAN_BATCH = 10
#: Memory the frames decoded ahead may take for decoding beside the analysis [bytes] (see
#: scan_video): 1920x1080 and smaller; larger frames are decoded in turns with the analysis.
BESIDE_MAX_BYTES = 256 * 2 ** 20
#: Frames (the latest) a try to focus looks at.
FOCUS_FRAMES = 240
#: Share of a turn the marker must have covered before the search focuses on its path: a path
#: fitted to a shorter arc (a wheel starting slowly from rest) may miss the rest of the turn.
FOCUS_COVERAGE = 0.8
#: Share of the frames the marker must have been found in before the search focuses.
FOCUS_FOUND = 0.9
#: A detection next to a gap whose blob is smaller than this share of the marker's usual area is
#: the marker partly hidden (its centroid pulled off): dropped.
PARTIAL_AREA = 0.93
#: Found frames over which the marker's full area is taken (see :func:`_drop_partial`).
PARTIAL_REF_FRAMES = 121


#: Bounds of the options that size the work: a speed window beyond a minute and a frame rate
#: beyond any high-speed camera are typing errors (they ran for minutes or overflowed).
MAX_WINDOW_S = 60.0


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
    expected_rpm : (low, high) or None
        Expected speed range [rpm] (after ``invert``; ``(0, inf)`` for "forwards only"):
        resolves motions beyond half a turn per frame (aliasing), which are refused without it.
    track_hub : bool
        Follow the hub per frame (a camera that shakes or drifts); off: fixed image coordinates.
    decode_beside : bool or None
        Decode in a helper thread beside the analysis (less wall time with a second core
        free) rather than in turns with it in one thread (the least CPU time); ``None``: beside
        when other jobs leave a second core free (see :func:`scan_video`). The
        results are the same.
    decoders : int or None
        Decoders beside the analysis: 2 decode every other part of the video each (faster
        than OpenCV's own decoding; about two parts of frames in memory), 1 the whole video;
        ``None``: two where the video is long enough and its keyframes close enough (see
        :func:`split_part_frames`). The results are the same.
    """

    rois: tuple[tuple[int, tuple[int, int, int, int] | None], ...] = ((1, None),)
    marker: MarkerSpec = field(default_factory=MarkerSpec)
    invert: bool = False
    fps: float | None = None
    window_s: float = DEFAULT_WINDOW_S
    min_found: float = DEFAULT_MIN_FOUND
    seed: int = 0
    expected_rpm: tuple[float, float] | None = None
    track_hub: bool = True
    decode_beside: bool | None = None
    decoders: int | None = None

    def __post_init__(self) -> None:
        if self.decoders not in (None, 1, 2):
            raise VideoError(f"decoders must be 1 or 2, got {self.decoders}")
        wheels = [w for w, _ in self.rois]
        if not wheels or len(set(wheels)) != len(wheels):
            raise VideoError("give each wheel at most one --roi")
        if not 0.0 <= self.min_found <= 1.0:
            raise VideoError(f"--min-found must be within 0..1, got {self.min_found}")
        if not 0 < self.window_s <= MAX_WINDOW_S:
            raise VideoError(f"--window must be > 0 s and at most {MAX_WINDOW_S:g} s, got "
                             f"{self.window_s}")
        check_fps(self.fps)
        if self.expected_rpm is not None:
            lo, hi = self.expected_rpm
            if math.isnan(lo) or math.isnan(hi) or not lo < hi:
                raise VideoError(f"expected speed range {lo}..{hi} rpm: need low < high")


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


def scan_video(path: str | Path, detectors_for: Callable[[tuple[int, int]], Sequence],
               progress: Callable[[int, int], None] | None = None,
               decode_beside: bool | None = None, decoders: int | None = None):
    """Decode every frame once and run the detectors on it.

    ``decode_beside``: decode in helper threads while this one analyses (default: when other
    jobs leave :data:`BESIDE_IDLE_CORES` of a second core free by
    :func:`~mecanum_hil._cores.idle_cores`, and four runs of frames fit in
    :data:`BESIDE_MAX_BYTES`); else decode and analyse in turns
    in this thread. ``decoders`` (beside only): 2 decodes every other part of the video in
    each of two threads (:func:`~mecanum_hil.vision.video.decoded_in_segments`), 1 the whole
    video in one; default: two where :func:`split_part_frames` finds the video long enough
    and its keyframes close enough. The results are the same in every mode (two decoders are
    checked frame for frame where their parts meet; where they disagree the video is decoded
    again in one piece).

    Returns ``(info, stamps [s], per-detector lists of per-frame results, detectors)``.
    """
    try:
        return _scan_video(path, detectors_for, progress, decode_beside, decoders)
    except SegmentMismatchError:
        return _scan_video(path, detectors_for, progress, True, 1)


def split_part_frames(path: str | Path, info: VideoInfo, forced: bool = False) -> int:
    """Frames per part when two decoders share a video (see :func:`scan_video`); 0: one.

    Parts of about :data:`SPLIT_PART_FRAMES`, as many for each decoder, a multiple of
    :data:`SCAN_BATCH`; 0 where not even a run of frames ahead fits the memory budget
    (:func:`split_ahead_frames`). Unless ``forced`` (``decoders=2``), also: at least
    :data:`SPLIT_SEEK_PARTS` times what a seek decodes in vain
    (:data:`~mecanum_hil.vision.video.SEEK_BACK_FRAMES` and the keyframe interval, read from
    the container's first packets), and the second part longer than that.
    """
    frames = info.frame_count
    if not split_ahead_frames(info, SPLIT_PART_FRAMES) or (not forced
                                                            and frames < SPLIT_PART_FRAMES):
        return 0
    pairs = max(1, round(frames / (2 * SPLIT_PART_FRAMES)))
    part = max(1, math.ceil(frames / (2 * pairs)))
    if not forced:
        gop = keyframe_interval(path)
        if gop is None:
            return 0
        waste = SEEK_BACK_FRAMES + gop
        part = max(part, SPLIT_SEEK_PARTS * waste)
        if frames - part < waste:
            return 0  # the second decoder's share would not pay for its seek
    return math.ceil(part / SCAN_BATCH) * SCAN_BATCH


def split_ahead_frames(info: VideoInfo, part: int) -> int:
    """Frames each of two decoders may decode ahead of the analysis: a whole part, fewer
    where what they hold would pass :data:`BESIDE_MAX_BYTES`; 0 where not even a run fits.

    Held at most: per decoder its frames ahead and a run in its queue, the frames compared
    where parts meet and a run being decoded; one run analysed. (bench_video, parts of 80
    frames: a whole part ahead was 10-15 % faster than half of one at 640x480, whose frames
    then take about 200 MB in all; at 1280x720, 20 frames ahead still gain most of it.)
    """
    frame_bytes = max(1, 3 * info.width_px * info.height_px)
    room = BESIDE_MAX_BYTES // frame_bytes - 5 * SCAN_BATCH - 2 * MEETING_FRAMES
    ahead = min(part, room // 2) // SCAN_BATCH * SCAN_BATCH
    return ahead if ahead >= SCAN_BATCH else 0


#: Frames per part, about, when two decoders share a video (see :func:`split_part_frames`):
#: fewer parts, fewer seeks (each decodes 16-28 frames in vain); more, an even share at the
#: end and less memory (bench_video: 60-120 frames were alike at 640x480).
SPLIT_PART_FRAMES = 80
#: A part is at least this many times the frames a seek decodes in vain.
SPLIT_SEEK_PARTS = 2


def _scan_video(path: str | Path, detectors_for: Callable[[tuple[int, int]], Sequence],
                progress: Callable[[int, int], None] | None, decode_beside: bool | None,
                decoders: int | None):
    """:func:`scan_video` in one of its modes (SegmentMismatchError: decode in one piece)."""
    cap, info = open_video(path, decoder_threads=1)
    if decode_beside is None:
        # up to four runs of frames in memory: analysed, two waiting, being decoded
        held = 4 * SCAN_BATCH * 3 * info.width_px * info.height_px
        decode_beside = _idle_cores() >= BESIDE_IDLE_CORES and held <= BESIDE_MAX_BYTES
    # FFmpeg decodes on one thread either way: its frame threads cost 5-50 % more CPU time
    # (see open_video), and beside the analysis they only slowed the whole down.
    # Beside: what the user waits for is the wall clock; with a second core free decoding and
    # analysis overlap (10-35 % less wall time than in turns), at 5-15 % more CPU time (frames
    # cross cores, and the decoding thread waits for the GIL the analysis holds). With another
    # job busy on the second core it is 0-10 % slower than in turns (bench/bench_video.py).
    # Two decoders beside (each on one FFmpeg thread, every other part of the video): their
    # pace together passes the baseline's; what they cost on top of one is OpenCV's seek at
    # each part (it decodes from a keyframe before), 25-40 % more CPU time (bench_video).
    # In turns: each frame is looked at while still in the core's cache: the least CPU time.
    # Frames are decoded into the same few buffers again (no fresh megabyte of memory per
    # frame); the buffer last handed back is decoded into first (a stack).
    free: queue.Queue = queue.LifoQueue()
    runs = None
    try:
        # Inside the try: a region outside the frame must not leave the file open.
        detectors = detectors_for((info.width_px, info.height_px))
        results: list[list] = [[] for _ in detectors]
        stamps: list[float] = []
        next_focus = FOCUS_AFTER_FRAMES
        reported = 0
        part = 0
        if decode_beside and decoders != 1:
            part = split_part_frames(path, info, forced=decoders == 2)
        if part:
            runs = decoded_in_segments(path, cap, part, SCAN_BATCH, free,
                                       ahead=split_ahead_frames(info, part))
        else:
            runs = (_runs_beside(cap, free) if decode_beside
                    else _runs_in_turns(cap, free, detectors))
        for run in runs:
            for index, _, frame in run:
                if frame.shape[1] != info.width_px or frame.shape[0] != info.height_px:
                    raise VideoError(f"{path}: frame {index} has another size than the first")
            next_focus = _scan_run(run, detectors, results, stamps, next_focus, free)
            if progress is not None and (not len(stamps) % SCAN_BATCH or len(run) > 1):
                progress(len(stamps), info.frame_count)
                reported = len(stamps)
        if progress is not None and stamps and len(stamps) != reported:
            progress(len(stamps), info.frame_count)
    finally:
        try:
            if runs is not None:
                runs.close()  # the helper thread is stopped before the file is closed
        finally:
            cap.release()  # even when a second Ctrl-C ends the wait for the thread
    return info, np.array(stamps, dtype=float), results, detectors


#: Idle cores (beyond this process's own) from which decoding goes beside the analysis: the
#: package's rule for working beside itself (:data:`mecanum_hil._cores.SPARE_CORE`, half a core).
BESIDE_IDLE_CORES = SPARE_CORE


def _runs_in_turns(cap, free: queue.Queue, detectors: Sequence) -> Iterator[list]:
    """Runs of :func:`~mecanum_hil.vision.video.iter_frames` items, decoded in this thread.

    Runs of SCAN_BATCH where a hub is read for a run at once; where no wheel's hub is read for
    a run (not tracked, or a still camera checked on single frames), single frames, each looked
    at as soon as it is decoded and its buffer decoded into again: one buffer, still in the
    core's cache, instead of SCAN_BATCH in turn (3-10 % of decoding's CPU time). The runs of
    the hub stay where they were (every SCAN_BATCH-th frame from the first): the results are
    the same.
    """
    run: list = []
    done = 0
    for item in iter_frames(cap, free):
        run.append(item)
        if (done + len(run)) % SCAN_BATCH and not all(
                not isinstance(det, _WheelScan) or det.single_frames for det in detectors):
            continue
        done += len(run)
        yield run
        run = []
    if run:
        yield run


def _runs_beside(cap, free: queue.Queue) -> Iterator[list]:
    """Runs of SCAN_BATCH :func:`~mecanum_hil.vision.video.iter_frames` items, decoded ahead
    in a helper thread; closing the generator stops and joins the thread."""
    return decoded_ahead(cap, maxsize=2, batch=SCAN_BATCH, free=free)


def _scan_run(run: list, detectors: Sequence, results: list[list], stamps: list[float],
              next_focus: int, free: queue.Queue) -> int:
    """Run the detectors on a run of :func:`~mecanum_hil.vision.video.iter_frames` items;
    hand the frames back to ``free`` and return the frame count of the next try to focus."""
    frames = [frame for _, _, frame in run]
    hubs = [det.hubs(frames) if isinstance(det, _WheelScan) else None for det in detectors]
    for j, (_, t, frame) in enumerate(run):
        stamps.append(t)
        for k, det in enumerate(detectors):
            results[k].append(det(frame) if hubs[k] is None
                              else det.candidates(frame, hubs[k][j]))
        if len(stamps) == next_focus:
            next_focus *= 2
            for k, det in enumerate(detectors):
                if isinstance(det, _WheelScan) and det.blobs.path is None:
                    det.focus(results[k])
    # Nothing keeps a frame (the results are new arrays): the decoder may reuse them.
    for frame in frames:
        free.put(frame)
    return next_focus


class _WheelScan:
    """One wheel's per-frame work: the hub's position, then the marker candidates near it.

    Each call returns ``(candidates, hub)``: rows ``(x, y, hue, weight, area)`` in the frame's
    coordinates, and ``(x, y, dark area)`` of the hub (NaN when not tracked).
    """

    def __init__(self, spec: MarkerSpec, roi, size, track_hub: bool) -> None:
        self.blobs = BlobDetector(spec, roi, size)
        self.hub = HubTracker(roi, size) if track_hub else None
        self.hub0: tuple[float, float] | None = None
        self.frames = 0
        self.first: list[tuple[float, float]] = []
        #: The camera looked still over the first frames: the hub is only checked every
        #: :data:`STILL_CHECK_FRAMES` frames until it moves (the frames between are then
        #: interpolated by :func:`~mecanum_hil.vision.hub.camera_offsets`).
        self.sparse = False

    @property
    def single_frames(self) -> bool:
        """Whether the hub is read on single frames from now on (not tracked, or a still
        camera: see :meth:`hubs`): nothing is gained by reading it for a run of frames."""
        return self.hub is None or self.sparse

    def shift(self, hub: tuple[float, float, float]) -> tuple[float, float]:
        """The hub's offset from the first frame [px] (0 when unknown)."""
        if self.hub0 is None or not math.isfinite(hub[0]):
            return (0.0, 0.0)
        return (hub[0] - self.hub0[0], hub[1] - self.hub0[1])

    def __call__(self, frame: np.ndarray):
        return self.candidates(frame, self.hubs([frame])[0])

    def candidates(self, frame: np.ndarray, hub: tuple[float, float, float]):
        """``(candidates, hub)`` of one frame whose hub :meth:`hubs` gave."""
        return self.blobs(frame, self.shift(hub)), hub

    def hubs(self, frames: list[np.ndarray]) -> list[tuple[float, float, float]]:
        """The hub in each of the next frames (NaN where it is not tracked: off, or a still
        camera between its checks), runs of tracked frames read at once."""
        out: list[tuple[float, float, float]] = []
        j = 0
        while j < len(frames):
            if self.hub is None or (self.sparse and self.frames % STILL_CHECK_FRAMES):
                found = [(math.nan, math.nan, 0.0)]
            elif self.sparse:
                found = [self.hub(frames[j])]
            else:
                # Up to where the still-camera test may change what is tracked.
                end = len(frames) if len(self.first) >= STILL_CHECK_AFTER else \
                    min(len(frames), j + STILL_CHECK_AFTER - len(self.first))
                found = self.hub.many(frames[j:end])
            for hub in found:
                if self.hub is not None and math.isfinite(hub[0]):
                    if self.hub0 is None:
                        self.hub0 = (hub[0], hub[1])
                    self._watch(hub)
                self.frames += 1
                out.append(hub)
            j += len(found)
        return out

    def _watch(self, hub: tuple[float, float, float]) -> None:
        """Decide after the first frames whether the camera is still; leave the sparse mode
        as soon as a check finds the hub moved."""
        if not math.isfinite(hub[0]):
            return
        if self.sparse:
            dx, dy = self.shift(hub)
            if math.hypot(dx, dy) > STILL_MOVED_PX:
                self.sparse = False
            return
        if len(self.first) < STILL_CHECK_AFTER:
            self.first.append((hub[0], hub[1]))
            if len(self.first) == STILL_CHECK_AFTER:
                spread = float(np.max(np.std(np.array(self.first), axis=0)))
                self.sparse = spread < STILL_CAMERA_PX

    def focus(self, results: list) -> None:
        """Find the marker's path in the frames so far (relative to the hub); when the marker
        has covered most of it, search only near it from now on."""
        # The latest frames only: the cost of a try stays bounded however long the video.
        results = results[-FOCUS_FRAMES:]
        n = len(results)
        # The marker can be found at most in the frames with a candidate: when they are too few
        # (a fender hides part of each turn), no path search can pass the test below.
        if sum(len(c) > 0 for c, _ in results) < FOCUS_FOUND * n:
            return
        allc = np.concatenate([c for c, _ in results])
        counts = np.array([len(c) for c, _ in results])
        frame_idx = np.repeat(np.arange(n), counts)
        shifts = np.array([self.shift(h) for _, h in results]).reshape(-1, 2)
        xy = allc[:, :2] - shifts[frame_idx]
        hue = allc[:, 2]
        try:
            track = select_track(frame_idx, xy, hue, n, self.blobs.size_px,
                                 np.random.default_rng(1), hypotheses=200)
        except VideoError:
            return
        if track.found.mean() >= FOCUS_FOUND and track.coverage >= FOCUS_COVERAGE:
            self.blobs.focus(track.path)


def _edges(found: np.ndarray) -> np.ndarray:
    """Found frames next to a frame without the marker."""
    return found & ~(np.r_[True, found[:-1]] & np.r_[found[1:], True])


def _drop_partial(track, area: np.ndarray, max_radius_px: float):
    """Drop detections next to a gap that look like the marker partly hidden (its centroid is
    pulled off): a blob smaller than the marker's running median, or off the path by far more
    than the others. Returns the track (path refitted) and the number dropped."""
    found = track.found.copy()
    n = found.size
    w = np.full(n, np.nan)
    w[found] = area[track.index[found]]
    frames = np.flatnonzero(found)
    if frames.size < 5:
        return track, 0
    # The marker's full size nearby: the upper quartile over many found frames (a wheel turning
    # slowly into hiding is partly hidden for dozens of frames; motion blur widens the blob at
    # speed, so a global figure would not do).
    k = min(PARTIAL_REF_FRAMES, frames.size) | 1
    padded = np.pad(w[frames], k // 2, mode="edge")
    full = np.percentile(np.lib.stride_tricks.sliding_window_view(padded, k), 75, axis=1)
    ref = np.full(n, np.nan)
    ref[frames] = full
    dropped = 0
    # Peel from the gap's edge inwards: a wheel turning slowly into hiding is partly hidden for
    # many frames.
    while True:
        bad = _edges(found) & (w < PARTIAL_AREA * ref)
        if not bad.any():
            break
        found[bad] = False
        dropped += int(bad.sum())
    for _ in range(10):
        track.found[:] = found
        track.xy_px[~found] = np.nan
        if dropped:
            track = refit_track(track, max_radius_px)
        rho, _ = track.path.unit(track.xy_px)
        resid = np.abs(rho - 1.0) * math.sqrt(track.path.a_px * track.path.b_px)
        mad = float(np.median(resid[found]))
        bad = _edges(found) & (resid > max(6.0 * mad, 0.3))
        if not bad.any():
            break
        found[bad] = False
        dropped += int(bad.sum())
    return track, dropped


def _wheel_angles(results: list, n: int, det: _WheelScan, seed: int, source: str):
    hub = np.array([h for _, h in results], dtype=float).reshape(-1, 3)
    if det.hub is not None:
        offsets, _ = camera_offsets(hub)
    else:
        offsets = np.zeros((n, 2))
    frame_idx = np.repeat(np.arange(n), [len(c) for c, _ in results])
    allc = np.concatenate([c for c, _ in results]) if results else np.empty((0, 5))
    xy = allc[:, :2] - offsets[frame_idx]
    hint = ("check --marker-hsv against the marker's colour in a frame, or give --roi around "
            "the wheel" if det.blobs.spec.kind == "hsv"
            else "give --marker-hsv, or --roi around the wheel")
    track = select_track(frame_idx, xy, allc[:, 2], n, det.blobs.size_px,
                         np.random.default_rng(seed), source=source, initial=det.blobs.path,
                         hint=hint)
    track, partial = _drop_partial(track, allc[:, 4], det.blobs.size_px)
    angle = np.full(n, np.nan)
    _, ang = track.path.unit(track.xy_px[track.found])
    angle[track.found] = ang
    return track, angle, offsets, partial


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
        return [_WheelScan(opts.marker, roi, size, opts.track_hub) for _, roi in opts.rois]

    info, stamps, per_wheel, detectors = scan_video(path, make, progress, opts.decode_beside,
                                                    opts.decoders)
    n = stamps.size
    if n < 3:
        raise VideoError(f"{src}: only {n} frame(s) could be decoded (empty or corrupt video)")
    warnings: list[str] = []
    if info.frame_count and n < info.frame_count - 1:
        warnings.append(f"the video ends after {n} of the {info.frame_count} frames its header "
                        "declares (truncated?); measured what could be decoded")
    timing = frame_times(stamps, info.fps_nominal, opts.fps, src)
    damaged = container_mismatch(path) if opts.fps is None else None
    if damaged is not None:
        warnings.append(f"the file does not start like {damaged} (damaged, or cut at its "
                        "start?): FFmpeg read a bare stream, whose frame times are its guess "
                        f"({timing.fps:g} fps); give --fps if you know the camera's rate")
    if timing.variable:
        warnings.append("variable frame rate: speeds use the frame timestamps")
    rec = empty_like_times(timing.t_s)
    wheel_rpm = rec.wheel_rpm.copy()
    extra: dict[str, list[str]] = {}
    wheels_summary = []
    for (wheel, roi), cands, det in zip(opts.rois, per_wheel, detectors, strict=True):
        where = f"{src}, wheel {wheel}"
        angle, geom = _wheel_angles_and_path(cands, n, det, opts, wheel, where, warnings)
        found = np.isfinite(angle)
        share = float(found.mean())
        if share < opts.min_found:
            raise VideoError(f"{where}: marker found in only {100 * share:.0f}% of the frames "
                             f"(need {100 * opts.min_found:.0f}%, see --min-found)")
        est = estimate_speed(timing.t_s, angle, opts.window_s, opts.invert, opts.expected_rpm)
        rpm, turns, outliers = est.rpm, est.turns, est.outliers
        _speed_warnings(est, wheel, timing, opts, where, warnings)
        wheel_rpm[:, wheel - 1] = rpm
        extra[f"wheel{wheel}_turns"] = ["" if not math.isfinite(v) else f"{v:.6f}" for v in turns]
        wheels_summary.append(_wheel_summary(wheel, roi, found, outliers, est, geom))
    summary = _video_summary(src, n, timing, info, opts, wheels_summary, warnings)
    meta = {"source": "mecanum-hil measure-video", "tool_version": __version__,
            "source_video": src, "fps": summary["fps"], "timing": timing.source,
            "method": summary["method"], "offset_s": None,
            "wheels": wheels_summary, "marker": opts.marker.kind, "invert": opts.invert}
    rec = rec.with_values(wheel_rpm=wheel_rpm, extra=extra, metadata=meta)
    return VideoMeasurement(rec, summary, tuple(warnings))


def _wheel_angles_and_path(cands, n: int, det, opts: MeasureOptions, wheel: int, where: str,
                           warnings: list[str]) -> tuple[np.ndarray, dict[str, Any]]:
    """The marker's angle in each frame [rad] and its path's geometry for the summary;
    warns when the path is a poor fit or too short an arc to tell its shape."""
    if opts.marker.kind == "aruco":
        from .aruco import aruco_angles

        return aruco_angles(cands, where)
    track, angle, offsets, partial = _wheel_angles(cands, n, det, opts.seed, where)
    moved = float(np.max(np.hypot(*(offsets - np.median(offsets, axis=0)).T)))
    geom = {"path": track.shape, "centre_px": [round(track.path.cx_px, 2),
                                               round(track.path.cy_px, 2)],
            "axes_px": [round(track.path.a_px, 2), round(track.path.b_px, 2)],
            "axis_angle_deg": round(track.path.angle_deg, 2),
            "view_tilt_deg": round(track.path.tilt_deg, 1),
            "path_coverage": round(track.coverage, 3),
            "path_residual_px": round(track.residual_px, 3),
            "partial_dropped": partial,
            "hub": "not tracked" if det.hub is None else
            ("tracked" if moved > 0 else "still"),
            "camera_motion_px": round(moved, 2)}
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
    return angle, geom


def _wheel_summary(wheel: int, roi, found: np.ndarray, outliers: int, est,
                   geom: dict[str, Any]) -> dict[str, Any]:
    """One wheel's entry in the summary: what was found, the speeds, the path."""
    speeds = est.rpm[np.isfinite(est.rpm)]
    return {
        "wheel": wheel, "roi": list(roi) if roi is not None else None,
        "found_fraction": round(float(found.mean()), 4), "frames_found": int(found.sum()),
        "outliers_dropped": outliers,
        "speed_samples": int(speeds.size),
        "mean_rpm": round(float(speeds.mean()), 3) if speeds.size else None,
        "max_abs_rpm": round(float(np.abs(speeds).max()), 3) if speeds.size else None,
        "aliasing": est.aliasing, "aliased_frames": int(est.aliased.sum()),
        "gaps": [g.as_dict() for g in est.gaps],
        "gaps_unbridged": sum(not g.bridged for g in est.gaps),
        **geom}


def _video_summary(src: str, n: int, timing: FrameTiming, info, opts: MeasureOptions,
                   wheels_summary: list[dict[str, Any]], warnings: list[str]
                   ) -> dict[str, Any]:
    """The whole video's summary (``--summary``): timing, method, wheels, warnings."""
    return {
        "video": src, "frames": n, "fps": round(timing.fps, 4),
        "fps_declared": None if math.isnan(info.fps_nominal) else info.fps_nominal,
        "duration_s": round(float(timing.t_s[-1]), 4), "timing": timing.source,
        "variable_frame_rate": timing.variable, "size_px": [info.width_px, info.height_px],
        "marker": opts.marker.kind, "method": _method(opts, timing),
        "wheels": wheels_summary, "offset_s": None, "warnings": warnings,
        "aliasing": any(w["aliasing"] for w in wheels_summary),
        "expected_rpm": None if opts.expected_rpm is None else
        [None if math.isinf(v) else v for v in opts.expected_rpm],
    }


def _speed_warnings(est, wheel: int, timing: FrameTiming, opts: MeasureOptions, where: str,
                    warnings: list[str]) -> None:
    """Warn about aliasing and unbridged gaps; refuse a wheel whose speeds are mostly aliased."""
    t = timing.t_s
    if est.aliasing:
        first = float(t[int(np.argmax(est.aliased))])
        limit = 30.0 * timing.fps
        share = float(np.isfinite(est.rpm).mean())
        msg = (f"aliasing at t={first:.3f} s: the marker moves about half a turn or more "
               f"between frames (the limit is {limit:.0f} rpm at this frame rate); the "
               f"direction is ambiguous there")
        if share < max(opts.min_found, ALIASED_MIN_SHARE):
            raise VideoError(f"{where}: {msg}; a speed is left for only {100 * share:.0f}% of "
                             "the frames: film at a higher frame rate, or give the expected "
                             "sign or speed range (--speed-range)")
        warnings.append(f"wheel {wheel}: {msg}; no speed is written for "
                        f"{int(est.aliased.sum())} frames (give --speed-range to resolve them)")
    if opts.expected_rpm is None:
        # Accepted, but past a quarter turn a frame the folded reading is the slower one of two
        # that give the same images: a wheel steadily beyond the limit is read as a slower one
        # turning the other way, and nothing in the images tells.
        per_frame = np.abs(est.rpm) / (60.0 * timing.fps)
        fast = np.flatnonzero(np.isfinite(per_frame) & (per_frame > FAST_STEP_TURNS))
        if fast.size:
            k = int(fast[0])
            s = float(est.rpm[k]) / (60.0 * timing.fps)
            other = (s - math.copysign(1.0, s)) * 60.0 * timing.fps
            warnings.append(
                f"wheel {wheel}: from t={float(t[k]):.3f} s the marker moves {abs(s):.2f} turn "
                f"a frame ({est.rpm[k]:.0f} rpm; {fast.size} frames): the same images come from "
                f"{other:.0f} rpm, which this frame rate cannot tell apart; give --speed-range "
                "(or its sign) if the wheel may turn that fast")
    unbridged = [g for g in est.gaps if not g.bridged and g.reason != "aliasing"]
    if unbridged:
        g = unbridged[0]
        warnings.append(
            f"wheel {wheel}: the marker was hidden in {len(unbridged)} gap(s) too long to count "
            f"the turns across (first {g.start_s:.2f}-{g.end_s:.2f} s: {g.reason}); the speed "
            "is measured on both sides, the angle (turns) restarts after each")


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
