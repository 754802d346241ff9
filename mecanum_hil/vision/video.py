"""Video files in and out through OpenCV (the I/O edge of the vision stage).

Everything OpenCV can decode is read; frame times come from the container's timestamps when it
has usable ones, else from the nominal frame rate. ``cv2`` errors and failures become
:class:`~mecanum_hil.errors.VideoError` here.
"""

from __future__ import annotations

import contextlib
import math
import os
import queue
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import VideoError
from ..io.paths import part_path

#: Codec chosen by file extension; all write and read back with opencv-python-headless. H.264
#: (``avc1``) has no encoder in the headless wheel; VP8 (``.webm``) is the H.264-like codec it
#: offers (motion-compensated inter-frame prediction, in-loop deblocking); VP9 encodes too
#: slowly here (over 0.5 s a frame).
FOURCC_BY_SUFFIX = {".mp4": "mp4v", ".m4v": "mp4v", ".mov": "mp4v", ".avi": "MJPG",
                    ".mkv": "MJPG", ".webm": "VP80"}

#: Coarsest container clock whose rounding of a constant frame rate is undone [s] (WebM and
#: Matroska timestamps are whole milliseconds).
TIMESTAMP_RESOLUTION_S = 0.001
#: Relative spread of frame intervals above which a video counts as variable frame rate.
VARIABLE_RATE_TOLERANCE = 0.02
#: Bounds of ``--fps`` [1/s]: from a time-lapse camera's 0.1 frames per second (one frame every
#: 10 s; below it the frame times of an ordinary video, 1e-5 fps, would be days) to beyond any
#: high-speed camera. Outside them the value is a typing error, refused.
MIN_FPS = 0.1
MAX_FPS = 100_000.0


@dataclass(frozen=True)
class VideoInfo:
    """What the container says about a video.

    Attributes
    ----------
    path : str
    fps_nominal : float
        Frame rate the container declares [1/s]; NaN when it declares none.
    frame_count : int
        Frames the container declares (0 when unknown; may be wrong for a truncated file).
    width_px, height_px : int
        Frame size [px].
    """

    path: str
    fps_nominal: float
    frame_count: int
    width_px: int
    height_px: int


@contextlib.contextmanager
def _stderr_silenced():
    """Process-wide stderr (file descriptor 2) to /dev/null for the block: native code that
    prints there directly; Python's own ``sys.stderr`` writes are flushed first."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):  # no real descriptor 2 (embedded, captured)
        yield
        return
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def _capture(cv2, p: Path, decoder_threads: int | None):
    """``cv2.VideoCapture`` of ``p``: FFmpeg with ``decoder_threads`` when given and it opens,
    else whatever backend OpenCV picks."""
    if decoder_threads is not None:
        cap = cv2.VideoCapture(str(p), cv2.CAP_FFMPEG,
                               [cv2.CAP_PROP_N_THREADS, int(decoder_threads)])
        if cap.isOpened():
            return cap
        cap.release()
    return cv2.VideoCapture(str(p))


def open_video(path: str | Path, decoder_threads: int | None = None):
    """Open a video for reading; return ``(capture, VideoInfo)``.

    ``decoder_threads`` caps FFmpeg's decoding threads (default: OpenCV's, one per core). One
    is the cheapest in CPU time (FFmpeg's frame threads cost 5-50 % more CPU time for mp4v and
    MJPG on this 2-core machine, varying with its load); measure-video decodes on one, in turns
    with its analysis or in a helper thread beside it (see its ``scan_video``).

    Raises
    ------
    VideoError
        The file is missing, or OpenCV cannot open or decode its first frame.
    """
    import cv2

    # FFmpeg's own complaints ("moov atom not found") would come on top of our one-line error;
    # a user who wants them sets OPENCV_FFMPEG_LOGLEVEL.
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
    p = Path(path)
    if not p.exists():
        raise VideoError(f"{p}: file not found")
    if p.is_dir():
        raise VideoError(f"{p}: is a folder, not a video")
    # and OpenCV's own warnings while it tries its backends ("backend is generally available
    # but can't be used to capture by name", "Unexpected element"): the error below says it
    quiet = getattr(getattr(cv2, "utils", None), "logging", None)
    level = quiet.getLogLevel() if quiet is not None else None
    try:
        if quiet is not None:
            quiet.setLogLevel(quiet.LOG_LEVEL_SILENT)
        with _stderr_silenced():  # its AVI parser writes to the C stream directly
            cap = _capture(cv2, p, decoder_threads)
    except cv2.error as err:
        raise VideoError(f"{p}: OpenCV cannot open it: {err}") from err
    finally:
        if level is not None:
            quiet.setLogLevel(level)
    if not cap.isOpened():
        raise VideoError(f"{p}: not a video OpenCV can decode (corrupt, truncated or unknown "
                         "format)")
    fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
    info = VideoInfo(str(p), fps if math.isfinite(fps) and 0.5 < fps < 10000 else math.nan,
                     max(0, int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)),
                     int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
                     int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
    return cap, info


def iter_frames(cap, free: queue.Queue | None = None, start: int = 0
                ) -> Iterator[tuple[int, float, np.ndarray]]:
    """Yield ``(index, timestamp [s] or NaN, BGR frame)`` until the video ends.

    ``free``: frames the consumer is done with, decoded into again when they fit (no fresh
    megabyte of memory per frame: its page faults and cache misses cost decoding about a tenth
    of its time in measure-video's pipeline). ``start``: the index of the next frame ``cap``
    decodes (after a seek)."""
    import cv2

    index = start
    while True:
        buf = None
        if free is not None:
            try:
                buf = free.get_nowait()
            except queue.Empty:
                pass
        try:
            ok, frame = cap.read() if buf is None else cap.read(buf)
        except cv2.error as err:
            raise VideoError(f"decoding failed at frame {index}: {err}") from err
        if not ok or frame is None:
            return
        t_ms = cap.get(cv2.CAP_PROP_POS_MSEC)
        t_s = t_ms / 1000.0 if t_ms is not None and math.isfinite(t_ms) else math.nan
        yield index, t_s, frame
        index += 1


def _put_unless_stopped(out: queue.Queue, item, stop: threading.Event) -> bool:
    """Hand ``item`` over, waiting while the queue is full; False once ``stop`` is set."""
    while not stop.is_set():
        try:
            out.put(item, timeout=0.1)
            return True
        except queue.Full:
            continue
    return False


def decode_ahead(cap, out: queue.Queue, stop: threading.Event, batch: int = 0,
                 free: queue.Queue | None = None) -> None:
    """Decode every frame of ``cap`` into ``out`` (a helper thread's body).

    Puts the :func:`iter_frames` items (with ``batch`` > 0: lists of up to ``batch`` of them,
    fewer hand-overs), then ``None`` at the end or the exception that stopped decoding (the
    consumer re-raises it; the frames before it are handed over first). ``free``: see
    :func:`iter_frames`. Returns as soon as
    ``stop`` is set, also while the queue is full (a consumer that gave up never leaves this
    thread blocked).
    """
    run: list = []
    try:
        for item in iter_frames(cap, free):
            if batch > 0:
                run.append(item)
                if len(run) < batch:
                    continue
                item, run = run, []
            if not _put_unless_stopped(out, item, stop):
                return
        if run and not _put_unless_stopped(out, run, stop):
            return
        _put_unless_stopped(out, None, stop)
    except BaseException as err:  # handed to the consumer, which re-raises it
        if run and not _put_unless_stopped(out, run, stop):
            return
        _put_unless_stopped(out, err, stop)


def decoded_ahead(cap, maxsize: int, batch: int = 0, free: queue.Queue | None = None,
                  join_timeout_s: float | None = None) -> Iterator[tuple | list]:
    """Yield what :func:`decode_ahead` decodes in a helper thread, until the video ends.

    Parameters
    ----------
    cap : cv2.VideoCapture
        The open video; the caller keeps owning it (and releases it after closing this
        generator).
    maxsize : int
        Items decoded ahead at most [items] (the queue's size).
    batch : int
        With ``batch`` > 0: lists of up to ``batch`` :func:`iter_frames` items [frames].
    free : queue.Queue or None
        Frame buffers to decode into again; see :func:`iter_frames`.
    join_timeout_s : float or None
        Longest wait for the helper thread when stopping it [s]; None waits until it ends.

    Yields
    ------
    tuple or list
        :func:`iter_frames` items ``(index, timestamp [s] or NaN, BGR frame)``, or lists of
        them with ``batch`` > 0.

    Raises
    ------
    BaseException
        Whatever stopped decoding, re-raised here after the frames before it.

    Notes
    -----
    The thread starts at the first ``next()``. Closing the generator (or its end, or an error)
    stops the thread and joins it: close it deterministically (``contextlib.closing`` or
    ``.close()`` in a ``finally``) before releasing ``cap``.
    """
    q: queue.Queue = queue.Queue(maxsize=maxsize)
    stop = threading.Event()
    worker = threading.Thread(target=decode_ahead, args=(cap, q, stop, batch, free),
                              daemon=True)
    worker.start()
    try:
        while True:
            item = q.get()
            if item is None:
                return
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        worker.join(timeout=join_timeout_s)


#: Frames OpenCV's seek decodes before the frame it seeks to, on top of those from the keyframe
#: before: it seeks to 16 frames earlier, then back to a keyframe (``cap_ffmpeg_impl.hpp``).
SEEK_BACK_FRAMES = 16
#: Frames compared where two decoders' parts meet (see :func:`decoded_in_segments`): the first
#: after a seek, and the next, whose decoding rests on references the seek had to rebuild.
MEETING_FRAMES = 2


class SegmentMismatchError(Exception):
    """Two decoders disagree where their parts of a video meet (a seek that does not land on
    the frame it was asked for, or decodes it differently): :func:`decoded_in_segments`'s
    caller decodes the video in one piece instead. Never reaches the user."""


_SEEK_FAILED = object()
_END = object()


def keyframe_interval(path: str | Path, max_packets: int = 600) -> int | None:
    """The longest run between keyframes among a video's first packets [frames], read from
    the container without decoding; None when its packets cannot be read that way or fewer
    than two keyframes are among them."""
    import cv2

    try:
        with _stderr_silenced():
            raw = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG, [cv2.CAP_PROP_FORMAT, -1])
    except cv2.error:
        return None
    keys: list[int] = []
    read = 0
    try:
        if not raw.isOpened():
            return None
        while read < max_packets and raw.grab():
            if raw.get(cv2.CAP_PROP_LRF_HAS_KEY_FRAME):
                keys.append(read)
            read += 1
    except cv2.error:
        return None
    finally:
        raw.release()
    if len(keys) < 2:
        return None
    runs = np.diff(keys).tolist()
    if read == max_packets:  # the run still open at the end of the scan counts too
        runs.append(read - keys[-1])
    return int(max(runs))


def _decode_segments(cap, first: int, segment: int, last_start: int, batch: int,
                     out: queue.Queue, stop: threading.Event, free: queue.Queue | None) -> None:
    """Decode every other part of ``segment`` frames, from part ``first``, into ``out`` (a
    helper thread's body for :func:`decoded_in_segments`).

    Per part: runs of up to ``batch`` :func:`iter_frames` items (frame index from the start
    of the video), then ``(_END, overlap)``: ``overlap`` is the first
    :data:`MEETING_FRAMES` frames of the next part as this decoder decodes them without a seek
    (empty at the end of the video). The part from ``last_start`` on runs to the end of the
    video (the declared frame count may be short). A seek that fails, raises or does not land on
    its frame puts ``_SEEK_FAILED``; an error is put after the frames before it.
    """

    part = first
    run: list = []
    try:
        while not stop.is_set():
            start = part * segment
            if start > last_start:  # the other decoder reads to the end
                return
            if start and not _seek(cap, start):
                _put_unless_stopped(out, _SEEK_FAILED, stop)
                return
            last = start >= last_start
            count, overlap = 0, []
            for item in iter_frames(cap, free, start):
                if not last and count >= segment:
                    overlap.append(item)
                    if len(overlap) == MEETING_FRAMES:
                        break
                    continue
                run.append(item)
                count += 1
                if len(run) == batch:
                    if not _put_unless_stopped(out, run, stop):
                        return
                    run = []
            if run and not _put_unless_stopped(out, run, stop):
                return
            run = []
            if not _put_unless_stopped(out, (_END, overlap), stop) or not overlap:
                return
            part += 2
    except BaseException as err:  # handed to the consumer, which re-raises it in its place
        if run and not _put_unless_stopped(out, run, stop):
            return
        _put_unless_stopped(out, err, stop)


def _seek(cap, frame: int) -> bool:
    """Seek ``cap`` to ``frame``; False when OpenCV refuses, raises, or lands elsewhere."""
    import cv2

    try:
        return bool(cap.set(cv2.CAP_PROP_POS_FRAMES, frame)
                    and cap.get(cv2.CAP_PROP_POS_FRAMES) == frame)
    except cv2.error:
        return False


def decoded_in_segments(path: str | Path, cap, segment: int, batch: int,
                        free: queue.Queue | None = None,
                        join_timeout_s: float | None = None,
                        ahead: int | None = None) -> Iterator[list]:
    """Yield runs of :func:`iter_frames` items in order, decoded by two decoders in helper
    threads, each taking every other part of ``segment`` frames.

    One decoder (FFmpeg on one thread) cannot keep pace with OpenCV's default decoding
    (FFmpeg's frame threads on every core); two, each on its own parts of the video, decode
    faster than either. Each part after the first starts with a seek; where two parts meet,
    the :data:`MEETING_FRAMES` frames after one decoder's part, decoded on without a seek, must
    equal the first frames of the next part, which the other decoder decoded after its seek
    (pixels and timestamps), or :class:`SegmentMismatchError` is raised: the results are those
    of decoding in one piece. (A video without timestamps whose frames repeat exactly, a still
    scene without noise, could pass a seek that lands a frame off: what it measures is the
    same.)

    Parameters
    ----------
    path : str or Path
        The video ``cap`` reads (opened a second time here).
    cap : cv2.VideoCapture
        The open video at its first frame; the caller keeps owning it (and releases it after
        closing this generator).
    segment : int
        Frames per part; a multiple of ``batch`` keeps the runs where one decoder puts them.
    batch : int
        Frames per run [frames].
    free : queue.Queue or None
        Frame buffers to decode into again; see :func:`iter_frames`.
    join_timeout_s : float or None
        Longest wait for each helper thread when stopping [s]; None waits until it ends.
    ahead : int or None
        Frames each decoder may hold decoded ahead of the consumer [frames]; default a whole
        part (see the Notes).

    Raises
    ------
    SegmentMismatchError
        The second decoder cannot open the video or seek in it, or disagrees with the first
        where their parts meet.
    BaseException
        Whatever stopped decoding, re-raised here after the frames before it.

    Notes
    -----
    Frames in memory at most: per decoder ``ahead`` and a run in its queue, a run being
    decoded and the :data:`MEETING_FRAMES` it compares; the consumer's run. Close the generator
    deterministically, as :func:`decoded_ahead`'s, before releasing ``cap``.
    """
    try:
        second, info = open_video(path, decoder_threads=1)
    except VideoError as err:  # out of file handles, the file replaced: decode in one piece
        raise SegmentMismatchError(f"cannot open a second decoder: {err}") from err
    last_start = max(0, (info.frame_count - 1) // segment * segment)
    # A whole part ahead: while the consumer takes one decoder's part, the other decodes
    # all of its next one (less ahead, less memory, and the decoders wait more).
    ahead = segment if ahead is None else max(1, ahead)
    size = -(-ahead // batch) + 1  # runs of frames ahead, and one more run or a part's end
    queues: list[queue.Queue] = [queue.Queue(maxsize=size) for _ in range(2)]
    stop = threading.Event()
    workers = [threading.Thread(target=_decode_segments, daemon=True,
                                args=(c, k, segment, last_start, batch, queues[k], stop, free))
               for k, c in enumerate((cap, second))]
    try:
        for worker in workers:
            worker.start()
        yield from _runs_in_order(queues, segment, free)
    finally:
        stop.set()
        for worker in workers:
            if worker.ident is not None:
                worker.join(timeout=join_timeout_s)
        second.release()


def _runs_in_order(queues: list[queue.Queue], segment: int,
                   free: queue.Queue | None) -> Iterator[list]:
    """Yield the runs of the two decoders' ``queues`` part by part (``segment`` frames each,
    alternating), checking where two parts meet (:func:`_meeting_frames`), until a part's end
    has nothing decoded on after it.

    Raises
    ------
    SegmentMismatchError
        A decoder could not seek, or disagrees with the other where their parts meet.
    BaseException
        Whatever a decoder raised.
    """
    part, expect = 0, []
    while True:
        q = queues[part % 2]
        while True:
            item = q.get()
            if isinstance(item, BaseException):
                raise item
            if item is _SEEK_FAILED:
                raise SegmentMismatchError(f"cannot seek to frame {part * segment}")
            if isinstance(item, tuple) and item[0] is _END:
                break
            if expect:
                _meeting_frames(expect, item, free)
            yield item
        if expect:
            raise SegmentMismatchError(f"the part from frame {expect[0][0]} ends early")
        expect = item[1]
        if not expect:
            return
        part += 1


def _meeting_frames(expect: list, run: list, free: queue.Queue | None) -> None:
    """Check the first frames of a part's ``run`` against those the other decoder decoded on
    past its own part (``expect``, consumed from the front), returning the compared buffers
    to ``free``."""
    meet = min(len(expect), len(run))
    for before, after in zip(expect[:meet], run[:meet], strict=True):
        _check_meeting(before, after)
        if free is not None:
            free.put(before[2])
    del expect[:meet]


def _check_meeting(before: tuple, after: tuple) -> None:
    """Where two parts meet: the frame decoded on without a seek (``before``) and after one
    (``after``) must be the same frame, decoded the same."""
    (i, t, a), (j, u, b) = before, after
    same_time = (math.isnan(t) and math.isnan(u)) or t == u
    if i != j or not same_time or a.shape != b.shape or not np.array_equal(a, b):
        raise SegmentMismatchError(f"the decoders disagree at frame {i}")


@dataclass(frozen=True)
class FrameTiming:
    """Frame times and how they were obtained.

    Attributes
    ----------
    t_s : ndarray, shape (N,)
        Time of each frame from the first one [s].
    fps : float
        Mean frame rate [1/s].
    source : str
        ``"timestamps"`` (container) or ``"nominal"`` (index / declared frame rate).
    variable : bool
        Whether the intervals vary more than :data:`VARIABLE_RATE_TOLERANCE`.
    """

    t_s: np.ndarray
    fps: float
    source: str
    variable: bool


def check_fps(fps: float | None) -> None:
    """A ``--fps`` within :data:`MIN_FPS` .. :data:`MAX_FPS` (None: not given)."""
    if fps is not None and not MIN_FPS <= fps <= MAX_FPS:
        raise VideoError(f"--fps must be within {MIN_FPS:g} .. {MAX_FPS:g} frames per second, "
                         f"got {fps:g}")


def frame_times(stamps_s: np.ndarray, fps_nominal: float, fps_override: float | None = None,
                source: str = "video") -> FrameTiming:
    """Frame times from container timestamps, or from the frame rate when those are unusable.

    Container timestamps are used when they are finite and strictly increasing; a video whose
    intervals vary is flagged ``variable`` (its timestamps are still used: the speed estimator
    takes uneven spacing). Timestamps that are the declared frame rate rounded to the
    container's clock (within :data:`TIMESTAMP_RESOLUTION_S` / 2) give the exact times of that
    rate. ``fps_override`` replaces both.

    Raises
    ------
    VideoError
        No usable timestamps and no frame rate (give ``--fps``).
    """
    n = len(stamps_s)
    if fps_override is not None:
        check_fps(fps_override)
        return FrameTiming(np.arange(n) / fps_override, float(fps_override), "override", False)
    st = np.asarray(stamps_s, dtype=float)
    if n >= 2 and np.isfinite(st).all() and (np.diff(st) > 0).all():
        t = st - st[0]
        if math.isfinite(fps_nominal) and fps_nominal > 0:
            grid = np.arange(n) / fps_nominal
            off_grid = float(np.max(np.abs(t - grid)))
            if 1e-6 < off_grid <= TIMESTAMP_RESOLUTION_S / 2 + 1e-9:
                # The declared rate, rounded to the container's clock (WebM and Matroska count
                # whole milliseconds: 33, 33, 34 ms at 30 fps): the exact times, not the rounded
                # ones, which would put 3 % errors into the speed at the ends of runs. (Exact
                # timestamps are kept as they are.)
                return FrameTiming(grid, float(fps_nominal), "timestamps", False)
        d = np.diff(t)
        med = float(np.median(d))
        variable = bool(np.max(np.abs(d - med)) > VARIABLE_RATE_TOLERANCE * med)
        return FrameTiming(t, float((n - 1) / t[-1]), "timestamps", variable)
    if math.isfinite(fps_nominal) and fps_nominal > 0:
        return FrameTiming(np.arange(n) / fps_nominal, float(fps_nominal), "nominal", False)
    raise VideoError(f"{source}: no frame rate and no usable frame timestamps; give --fps")


#: How a file of each container starts: (offset, bytes), any of them [-].
_CONTAINER_SIGNATURES = {
    "an MP4/QuickTime file": tuple((4, box) for box in (
        b"ftyp", b"moov", b"mdat", b"wide", b"free", b"skip", b"pnot", b"udta", b"junk",
        b"uuid", b"prfl", b"styp", b"sidx", b"moof")),  # the first boxes FFmpeg's probe takes
    "an AVI file": ((0, b"RIFF"),),
    "a Matroska/WebM file": ((0, b"\x1a\x45\xdf\xa3"),),
}
_CONTAINER_BY_SUFFIX = {".mp4": "an MP4/QuickTime file", ".m4v": "an MP4/QuickTime file",
                        ".mov": "an MP4/QuickTime file", ".avi": "an AVI file",
                        ".mkv": "a Matroska/WebM file", ".webm": "a Matroska/WebM file"}


def container_mismatch(path: str | Path) -> str | None:
    """The container a video's extension promises when its first bytes are not that
    container's (a file damaged or cut at its start: FFmpeg then reads a bare stream, whose
    frame rate it guesses); ``None`` when they are, or for an extension not known here."""
    p = Path(path)
    kind = _CONTAINER_BY_SUFFIX.get(p.suffix.lower())
    if kind is None:
        return None
    try:
        with p.open("rb") as fh:
            head = fh.read(12)
    except OSError:
        return None
    if any(head[o:o + len(sig)] == sig for o, sig in _CONTAINER_SIGNATURES[kind]):
        return None
    return kind


def fourcc_for(path: str | Path) -> str:
    """The codec used to write a file of this extension (``.mp4`` -> mp4v, ``.avi`` -> MJPG)."""
    suffix = Path(path).suffix.lower()
    if suffix not in FOURCC_BY_SUFFIX:
        raise VideoError(f"{path}: unsupported video extension '{suffix}' "
                         f"(use one of {', '.join(sorted(FOURCC_BY_SUFFIX))})")
    return FOURCC_BY_SUFFIX[suffix]


class VideoWriter:
    """Write BGR frames to a video file; the codec follows the extension (:func:`fourcc_for`).

    The frames go to a temporary file beside it (``.NAME.part.EXT``), put in place when the
    writer is closed normally: a render interrupted (Ctrl-C, SIGTERM) or failing leaves the
    previous video as it was and no part file, never a shorter video that plays as if whole.
    """

    def __init__(self, path: str | Path, fps: float, size_px: tuple[int, int]) -> None:
        import cv2

        self.path = Path(path)
        self._part = part_path(self.path)
        fourcc = fourcc_for(self.path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise VideoError(f"{self.path}: cannot create the folder {self.path.parent}: "
                             f"{err.strerror or err}") from err
        # FFmpeg takes VP8 in WebM only under its own tag and says so on stderr each time
        # ("tag 'VP80' is not supported ... format 'webm'"), then writes it right: not a
        # message for the user
        quiet = _stderr_silenced() if fourcc == "VP80" else contextlib.nullcontext()
        with quiet:
            self._writer = cv2.VideoWriter(str(self._part), cv2.VideoWriter_fourcc(*fourcc),
                                           float(fps), (int(size_px[0]), int(size_px[1])))
        if not self._writer.isOpened():
            self._part.unlink(missing_ok=True)
            raise VideoError(f"{self.path}: OpenCV cannot write {fourcc} video here")
        self.frames = 0

    def write(self, frame: np.ndarray) -> None:
        """Append one BGR uint8 frame."""
        self._writer.write(frame)
        self.frames += 1

    def close(self) -> None:
        """Finish the file and put it in place."""
        self._writer.release()
        if self._part.exists():
            try:
                os.replace(self._part, self.path)
            except OSError as err:
                self._part.unlink(missing_ok=True)
                raise VideoError(f"{self.path}: cannot write: {err.strerror or err}") from err

    def discard(self) -> None:
        """Stop writing and remove what was written (the previous video, if any, stays)."""
        self._writer.release()
        try:
            self._part.unlink(missing_ok=True)
        except OSError:
            pass

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is None:
            self.close()
        else:
            self.discard()
