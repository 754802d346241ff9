"""``measure-pose`` as a library: the robot's pose (X, Y, phi) from an overhead camera's video.

One pass over the video (decoding in a helper thread). Markers are found with OpenCV's ArUco
detector and sub-pixel corner refinement; after the first sighting each marker is searched only
in a window around where it was (the robot's window follows its motion), which keeps the cost
per frame small. Then:

1. **The static camera** from the floor markers over the whole video: each floor corner's image
   position is the median of its sightings (every ``floor_every``-th frame; sightings more than
   1 px from the median, e.g. partly hidden, are dropped), then one ``solvePnP`` (iterative
   Levenberg-Marquardt from SQPnP's start) on all floor corners.
2. **The robot's marker on its known plane.** Each corner is undistorted and its ray cut with
   the plane ``z = height_m``; the four floor-plane points give the marker's position and yaw by
   a least-squares rigid fit (its size is known), three unknowns instead of solvePnP's six;
   the robot's pose follows from the marker's place on it.
3. **Time.** Along each run of consecutive frames with the marker, a local quadratic regression
   (Savitzky-Golay, centred, so it does not lag; sliding inward at the ends of a run) over
   ``window_s``; a frame far off its neighbours' fit (a corner caught on something) is dropped
   first. Frames without the marker stay empty.

:func:`measure_pose_plain` is the plain per-frame pipeline (detect, undistort, ``solvePnP`` of
the camera on that frame's floor markers and of the robot's marker), kept for comparison.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..errors import VideoError
from .camera import CameraModel, CameraPose, rays_to_plane
from .scene import UNIT_CORNERS, Scene, dictionary_by_name
from .video import check_fps, decoded_ahead, frame_times, open_video

#: Default smoothing window [s] (0 turns smoothing off).
DEFAULT_WINDOW_S = 0.2
#: A frame whose pose is this many robust standard deviations off its neighbours' fit is dropped.
OUTLIER_SIGMAS = 6.0


@dataclass(frozen=True)
class PoseOptions:
    """How to measure.

    Attributes
    ----------
    window_s : float
        Smoothing window [s]; 0: the per-frame poses as they are.
    floor_every : int
        Floor markers are looked at in every this many frames.
    fps : float or None
        Frame rate overriding the video's timestamps [1/s].
    min_found : float
        Smallest share of frames with the robot's marker (0..1); below it the result is refused.
    """

    window_s: float = DEFAULT_WINDOW_S
    floor_every: int = 5
    fps: float | None = None
    min_found: float = 0.2

    def __post_init__(self) -> None:
        if not (math.isfinite(self.window_s) and self.window_s >= 0):
            raise VideoError(f"--window must be >= 0 s, got {self.window_s}")
        if self.floor_every < 1:
            raise VideoError("floor_every must be >= 1")
        if not 0.0 <= self.min_found <= 1.0:
            raise VideoError(f"--min-found must be within 0..1, got {self.min_found}")
        check_fps(self.fps)


@dataclass(frozen=True)
class PoseMeasurement:
    """The robot's pose measured from a video.

    Attributes
    ----------
    t_s : ndarray, shape (N,)
        Video time of each frame [s] (0 at the first frame).
    pose : ndarray, shape (N, 3)
        ``(X [m], Y [m], phi [deg])`` per frame (smoothed), phi unwrapped; NaN where the
        marker was not seen.
    raw_pose : ndarray, shape (N, 3)
        The per-frame poses before smoothing.
    camera_pose : CameraPose
    reprojection_rms_px : float
        RMS distance of the floor corners from their reprojection [px].
    summary : dict
    warnings : tuple of str
    """

    t_s: np.ndarray
    pose: np.ndarray
    raw_pose: np.ndarray
    camera_pose: CameraPose
    reprojection_rms_px: float
    summary: dict[str, Any] = field(default_factory=dict)
    warnings: tuple[str, ...] = ()

    @property
    def found(self) -> np.ndarray:
        """Frames with a pose."""
        return np.isfinite(self.pose).all(axis=1)


def make_detector(dictionary: str, refinement: str = "apriltag"):
    """An ArUco detector for ``dictionary`` with sub-pixel corner refinement: ``"apriltag"``
    (OpenCV's AprilTag edge fit, the default) or ``"subpix"`` (``cornerSubPix``)."""
    import cv2

    params = cv2.aruco.DetectorParameters()
    if refinement == "apriltag":
        # on rendered markers with a known truth, SUBPIX's corners sat 0.15 px off tangentially
        # (all the same way round: a 0.2 deg heading bias), AprilTag's 0.01 px (docs/vision-pose.md)
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_APRILTAG
    elif refinement == "subpix":
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    else:
        raise VideoError(f"corner refinement must be 'apriltag' or 'subpix', got {refinement!r}")
    return cv2.aruco.ArucoDetector(dictionary_by_name(dictionary), params)


@functools.cache
def apriltag_corner_shift_px() -> float:
    """Where OpenCV's AprilTag corner refinement puts a corner, less where it is [px].

    The AprilTag code counts from the top-left pixel's outer corner, not its centre
    (AprilRobotics/apriltag#121): a sharp-edged marker whose edge lies at 9.5 px comes back at
    10.0 (on the overhead renders +0.43..0.45 px in x and y). Measured once on such a marker
    rather than assumed, so that an OpenCV which changes its convention is followed.
    """
    import cv2

    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    img = np.full((80, 80), 255, np.uint8)
    img[10:70, 10:70] = cv2.aruco.generateImageMarker(dictionary, 0, 60)
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_APRILTAG
    corners, ids, _ = cv2.aruco.ArucoDetector(dictionary, params).detectMarkers(img)
    if ids is None or len(ids) != 1:
        return 0.5  # what every OpenCV with this refinement has done so far
    want = np.array([[9.5, 9.5], [69.5, 9.5], [69.5, 69.5], [9.5, 69.5]])
    return float(np.mean(corners[0].reshape(4, 2) - want))


def detect(detector, gray: np.ndarray, offset=(0, 0)) -> dict[int, np.ndarray]:
    """Markers in a grey image: ``{id: corners (4, 2) [px]}`` (OpenCV's corner order, ``(0,
    0)`` at the centre of the top-left pixel), shifted by ``offset`` (the crop's top-left corner
    in the frame)."""
    import cv2

    corners, ids, _ = detector.detectMarkers(gray)
    if ids is None:
        return {}
    off = np.asarray(offset, dtype=float)
    if detector.getDetectorParameters().cornerRefinementMethod == \
            cv2.aruco.CORNER_REFINE_APRILTAG:
        off = off - apriltag_corner_shift_px()
    out: dict[int, np.ndarray] = {}
    for c, i in zip(corners, ids.ravel(), strict=True):
        if int(i) not in out:  # a second sighting of one id is a misreading: keep the first
            out[int(i)] = c.reshape(4, 2).astype(float) + off
    return out


def _window(corners: np.ndarray, frame_size: tuple[int, int], grow: float
            ) -> tuple[int, int, int, int]:
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    pad = grow * float(np.max(hi - lo)) + 12.0
    w, h = frame_size
    return (max(0, int(lo[0] - pad)), max(0, int(lo[1] - pad)),
            min(w, math.ceil(hi[0] + pad)), min(h, math.ceil(hi[1] + pad)))


class _Tracker:
    """Finds the floor markers and the robot's marker frame by frame (stateful)."""

    def __init__(self, scene: Scene, frame_size: tuple[int, int], floor_every: int) -> None:
        self.scene = scene
        self.size = frame_size
        self.floor_every = floor_every
        self.detector = make_detector(scene.dictionary)
        self.floor_ids = {m.id for m in scene.floor}
        self.floor_seen: dict[int, list[np.ndarray]] = {i: [] for i in self.floor_ids}
        self.floor_windows: dict[int, tuple[int, int, int, int]] = {}
        self.robot: list[np.ndarray | None] = []
        self.full_scans = 0

    def _crop_detect(self, frame: np.ndarray, win, upscale: int = 1) -> dict[int, np.ndarray]:
        import cv2

        x0, y0, x1, y1 = win
        gray = cv2.cvtColor(frame[y0:y1, x0:x1], cv2.COLOR_BGR2GRAY)
        if upscale == 1:
            return detect(self.detector, gray, (x0, y0))
        big = cv2.resize(gray, None, fx=upscale, fy=upscale, interpolation=cv2.INTER_CUBIC)
        # pixel centres: x_big = upscale * x + (upscale - 1) / 2
        off = (upscale - 1) / 2.0
        return {i: (c - off) / upscale + np.array([x0, y0], float)
                for i, c in detect(self.detector, big).items()}

    def __call__(self, index: int, frame: np.ndarray) -> None:
        rid = self.scene.robot.marker_id
        last = self.robot[-1] if self.robot else None
        prev = self.robot[-2] if len(self.robot) >= 2 else None
        found = None
        full = None
        missing_floor = len(self.floor_windows) < len(self.floor_ids)
        if last is not None:
            guess = last + (last - prev) if prev is not None else last
            win = _window(guess, self.size, 0.6)
            found = self._crop_detect(frame, win).get(rid)
            if found is None and float(np.ptp(last[:, 0]) + np.ptp(last[:, 1])) < 80.0:
                # a small marker the detector's thresholds missed: once more, twice as large
                found = self._crop_detect(frame, win, upscale=2).get(rid)
        if found is None:
            # a full look: the marker was lost (or never seen), or floor markers are missing
            full = self._crop_detect(frame, (0, 0, *self.size))
            self.full_scans += 1
            found = full.get(rid)
        elif missing_floor and index % (10 * self.floor_every) == 0:
            full = self._crop_detect(frame, (0, 0, *self.size))
            self.full_scans += 1
        self.robot.append(found)
        if full is not None:
            for i, c in full.items():
                if i in self.floor_ids:
                    self.floor_seen[i].append(c)
                    self.floor_windows[i] = _window(c, self.size, 0.5)
        elif index % self.floor_every == 0:
            for i, win in self.floor_windows.items():
                # past 30 sightings a marker's median hardly moves: look 6x less often
                if len(self.floor_seen[i]) >= 30 and index % (6 * self.floor_every):
                    continue
                c = self._crop_detect(frame, win).get(i)
                if c is not None:
                    self.floor_seen[i].append(c)


def scan(path: str | Path, per_frame: Callable[[int, np.ndarray], None],
         progress: Callable[[int, int], None] | None = None):
    """Decode every frame (in a helper thread) and hand it to ``per_frame(index, frame)``;
    return ``(VideoInfo, stamps [s])``."""
    cap, info = open_video(path)
    stamps: list[float] = []
    frames = decoded_ahead(cap, maxsize=8, join_timeout_s=5.0)
    try:
        for _, t, frame in frames:
            if frame.shape[1] != info.width_px or frame.shape[0] != info.height_px:
                raise VideoError(f"{path}: frame {len(stamps)} has another size than the first")
            per_frame(len(stamps), frame)
            stamps.append(t)
            if progress is not None:
                progress(len(stamps), info.frame_count)
    finally:
        frames.close()  # the helper thread is stopped before the file is closed
        cap.release()
    return info, np.array(stamps, dtype=float)


def estimate_camera_pose(camera: CameraModel, scene: Scene,
                         sightings: dict[int, list[np.ndarray]]
                         ) -> tuple[CameraPose, float, tuple[int, ...]]:
    """The static camera's pose from all sightings of the floor markers.

    Returns ``(pose, reprojection RMS [px], ids used)``.

    Raises
    ------
    VideoError
        No floor marker seen.
    """
    import cv2

    by_id = scene.floor_by_id()
    obj, img, used = [], [], []
    for i, seen in sorted(sightings.items()):
        if not seen:
            continue
        stack = np.stack(seen)
        med = np.median(stack, axis=0)
        keep = np.max(np.linalg.norm(stack - med, axis=2), axis=1) <= 1.0
        if keep.sum() >= max(1, 0.3 * len(stack)):
            med = stack[keep].mean(axis=0)
        obj.append(by_id[i].corners_m())
        img.append(med)
        used.append(i)
    if not used:
        raise VideoError("no floor marker found in the video: the camera's pose cannot be "
                         "estimated (check --scene's dictionary and ids)")
    obj_a = np.concatenate(obj).astype(np.float64)
    img_a = np.concatenate(img).astype(np.float64)
    k, d = camera.matrix, camera.dist
    if len(used) >= 2:
        ok, rvec, tvec = cv2.solvePnP(obj_a, img_a, k, d, flags=cv2.SOLVEPNP_SQPNP)
    else:
        ok, rvec, tvec = cv2.solvePnP(obj_a, img_a, k, d, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise VideoError("the camera's pose cannot be solved from the floor markers")
    rvec, tvec = cv2.solvePnPRefineLM(obj_a, img_a, k, d, rvec, tvec,
                                      (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100,
                                       1e-12))
    pose = CameraPose(rvec.ravel(), tvec.ravel())
    rms = float(np.sqrt(np.mean(np.sum((camera.project(obj_a, pose) - img_a) ** 2, axis=1))))
    return pose, rms, tuple(used)


def rigid_fit(model_xy: np.ndarray, world_xy: np.ndarray) -> tuple[float, float, float]:
    """Least-squares rotation and translation (no scale) taking ``model_xy`` onto
    ``world_xy``: ``(tx [m], ty [m], angle [rad])``."""
    mc = model_xy - model_xy.mean(axis=0)
    wc = world_xy - world_xy.mean(axis=0)
    angle = math.atan2(float(np.sum(mc[:, 0] * wc[:, 1] - mc[:, 1] * wc[:, 0])),
                       float(np.sum(mc[:, 0] * wc[:, 0] + mc[:, 1] * wc[:, 1])))
    c, s = math.cos(angle), math.sin(angle)
    t = world_xy.mean(axis=0) - model_xy.mean(axis=0) @ np.array([[c, s], [-s, c]])
    return float(t[0]), float(t[1]), angle


def robot_poses(camera: CameraModel, camera_pose: CameraPose, scene: Scene,
                corners: list[np.ndarray | None]) -> np.ndarray:
    """Per-frame robot pose ``(X, Y, phi_deg)`` from the robot marker's corners, the marker on
    its plane ``z = height_m`` (NaN where it was not seen); phi in (-180, 180]."""
    rm = scene.robot
    out = np.full((len(corners), 3), np.nan)
    idx = [i for i, c in enumerate(corners) if c is not None]
    if not idx:
        return out
    px = np.concatenate([corners[i] for i in idx])
    world = rays_to_plane(camera_pose, camera.normalised(px), rm.height_m).reshape(-1, 4, 2)
    model = UNIT_CORNERS * rm.size_m
    for k, i in enumerate(idx):
        if not np.isfinite(world[k]).all():
            continue
        mx, my, ang = rigid_fit(model, world[k])
        x, y, phi = rm.robot_pose(mx, my, math.degrees(ang))
        out[i] = (x, y, (phi + 180.0) % 360.0 - 180.0)
    return out


def _runs(found: np.ndarray) -> list[tuple[int, int]]:
    """``(start, end)`` (end exclusive) of each run of consecutive True."""
    edges = np.diff(np.concatenate([[0], found.astype(int), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True))


def local_quadratic(t: np.ndarray, y: np.ndarray, h: int) -> np.ndarray:
    """Value of a local quadratic regression over ``2h + 1`` samples at each sample (centred;
    the window slides inward at the ends). Columns of ``y`` are smoothed independently."""
    n = len(t)
    if h <= 0 or n < 3:
        return y.copy()
    half = min(h, (n - 1) // 2)
    out = np.empty_like(y)
    for i in range(n):
        a = min(max(i - half, 0), n - 2 * half - 1)
        b = a + 2 * half + 1
        tt = t[a:b] - t[i]
        basis = np.column_stack([np.ones(b - a), tt, tt * tt])
        coef = np.linalg.lstsq(basis, y[a:b], rcond=None)[0]
        out[i] = coef[0]
    return out


def smooth_pose(t_s: np.ndarray, raw: np.ndarray, window_s: float) -> tuple[np.ndarray, int]:
    """Heading unwrapped along the whole video, single-frame outliers dropped, then
    :func:`local_quadratic` over runs of consecutive frames. Returns ``(pose, outliers)``."""
    pose = raw.copy()
    found = np.isfinite(pose).all(axis=1)
    if found.any():
        f = np.flatnonzero(found)
        pose[f, 2] = np.degrees(np.unwrap(np.radians(pose[f, 2])))
    if window_s <= 0 or found.sum() < 3:
        return pose, 0
    fps = 1.0 / float(np.median(np.diff(t_s))) if len(t_s) > 1 else 30.0
    h = max(1, round(0.5 * window_s * fps))
    dropped = 0
    for a, b in _runs(found):
        if b - a < 5:
            continue
        fit = local_quadratic(t_s[a:b], pose[a:b], h)
        res = pose[a:b] - fit
        scale = 1.4826 * np.median(np.abs(res - np.median(res, axis=0)), axis=0) + \
            np.array([2e-4, 2e-4, 0.02])
        bad = (np.abs(res) > OUTLIER_SIGMAS * scale).any(axis=1)
        if bad.any():
            dropped += int(bad.sum())
            pose[a:b][bad] = np.nan
    found = np.isfinite(pose).all(axis=1)
    out = np.full_like(pose, np.nan)
    for a, b in _runs(found):
        out[a:b] = local_quadratic(t_s[a:b], pose[a:b], h)
    return out, dropped


def measure_pose(path: str | Path, camera: CameraModel, scene: Scene,
                 options: PoseOptions | None = None,
                 progress: Callable[[int, int], None] | None = None) -> PoseMeasurement:
    """Measure the robot's pose in every frame of an overhead video.

    Parameters
    ----------
    path : str or Path
    camera : CameraModel
        Intrinsics and distortion (``camera.toml``); its size must be the video's.
    scene : Scene
        Floor markers and the robot's marker (``scene.toml``).
    options : PoseOptions, optional
    progress : callable, optional
        ``progress(done, total)`` after each frame.

    Raises
    ------
    VideoError
        Undecodable video, size mismatch with the camera, no floor marker, the robot's marker
        in too few frames.
    """
    opts = options or PoseOptions()
    src = str(path)
    box: dict[str, _Tracker] = {}

    def per_frame(index: int, frame: np.ndarray) -> None:
        if "t" not in box:
            h, w = frame.shape[:2]
            if (w, h) != (camera.width_px, camera.height_px):
                raise VideoError(f"{src}: frames are {w}x{h} px but the camera file is for "
                                 f"{camera.width_px}x{camera.height_px}")
            box["t"] = _Tracker(scene, (w, h), opts.floor_every)
        box["t"](index, frame)

    info, stamps = scan(path, per_frame, progress)
    if len(stamps) < 3:
        raise VideoError(f"{src}: only {len(stamps)} frames decoded; need at least 3")
    tracker = box["t"]
    timing = frame_times(stamps, info.fps_nominal, opts.fps, src)
    cam_pose, rms, used = estimate_camera_pose(camera, scene, tracker.floor_seen)
    raw = robot_poses(camera, cam_pose, scene, tracker.robot)
    pose, outliers = smooth_pose(timing.t_s, raw, opts.window_s)
    n = len(stamps)
    found = np.isfinite(pose).all(axis=1)
    share = float(found.mean())
    if share < opts.min_found:
        raise VideoError(f"{src}: the robot's marker (id {scene.robot.marker_id}) was found in "
                         f"only {100 * share:.0f} % of the frames (--min-found "
                         f"{100 * opts.min_found:.0f} %)")
    warnings = _pose_warnings(n, info.frame_count, scene, used, rms)
    summary = {
        "video": src, "frames": n, "found": int(found.sum()), "found_share": round(share, 4),
        "fps": round(timing.fps, 4), "timing": timing.source,
        "size_px": [info.width_px, info.height_px],
        "camera_reprojection_rms_px": round(rms, 4),
        "camera_pose": cam_pose.summary(),
        "floor_markers_used": list(used),
        "floor_sightings": int(sum(len(v) for v in tracker.floor_seen.values())),
        "full_frame_scans": tracker.full_scans,
        "robot_marker_id": scene.robot.marker_id,
        "outliers_dropped": outliers,
        "window_s": opts.window_s,
        "method": (f"ArUco ({scene.dictionary}) with sub-pixel corners; static camera from "
                   f"{len(used)} floor markers over the video; robot marker on its plane "
                   f"z = {scene.robot.height_m:g} m; local quadratic over {opts.window_s:g} s"),
        "tool_version": __version__,
        "warnings": warnings,
    }
    return PoseMeasurement(timing.t_s, pose, raw, cam_pose, rms, summary, tuple(warnings))


def _pose_warnings(n: int, frame_count: int, scene: Scene, used, rms: float) -> list[str]:
    """What the summary warns of: a truncated video, floor markers unseen or too few, a
    camera pose that fits its sightings poorly (``rms`` [px])."""
    warnings = []
    if frame_count and n < frame_count - 1:
        warnings.append(f"the video ends after {n} of the {frame_count} frames its header "
                        "declares (truncated?); measured what could be decoded")
    missing = sorted({m.id for m in scene.floor} - set(used))
    if missing:
        warnings.append(f"floor markers never seen: {missing}")
    if len(used) < 2:
        warnings.append("only one floor marker seen: the camera's pose rests on four corners")
    if rms > 1.0:
        warnings.append(f"the floor markers reproject {rms:.2f} px RMS off their sightings: "
                        "check the scene's marker places and the camera file")
    return warnings


def measure_pose_plain(path: str | Path, camera: CameraModel, scene: Scene,
                       fps: float | None = None, refinement: str = "subpix"
                       ) -> tuple[np.ndarray, np.ndarray]:
    """The plain per-frame pipeline, for comparison: in each frame, detect every marker, the
    camera's pose by ``solvePnP`` on that frame's floor markers, the robot marker's by
    ``solvePnP`` (IPPE square), the robot's pose from the two. No static camera, no height
    constraint, no smoothing; OpenCV's usual ``cornerSubPix`` refinement unless
    ``refinement`` says ``"apriltag"``.

    Returns ``(t_s, pose (N, 3))``, NaN where the robot's marker or every floor marker is
    missing.
    """
    import cv2

    detector = make_detector(scene.dictionary, refinement)
    by_id = scene.floor_by_id()
    rm = scene.robot
    half = 0.5 * rm.size_m
    square = np.array([[-half, half, 0], [half, half, 0], [half, -half, 0], [-half, -half, 0]])
    k, d = camera.matrix, camera.dist
    rows: list[tuple[float, float, float]] = []

    def per_frame(index: int, frame: np.ndarray) -> None:
        seen = detect(detector, cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))
        floor = [i for i in seen if i in by_id]
        if rm.marker_id not in seen or not floor:
            rows.append((math.nan,) * 3)
            return
        obj = np.concatenate([by_id[i].corners_m() for i in floor])
        img = np.concatenate([seen[i] for i in floor])
        flag = cv2.SOLVEPNP_SQPNP if len(floor) >= 2 else cv2.SOLVEPNP_IPPE
        ok, rv, tv = cv2.solvePnP(obj, img, k, d, flags=flag)
        ok2, rm_rv, rm_tv = cv2.solvePnP(square, seen[rm.marker_id], k, d,
                                         flags=cv2.SOLVEPNP_IPPE_SQUARE)
        if not (ok and ok2):
            rows.append((math.nan,) * 3)
            return
        r_wc = cv2.Rodrigues(rv)[0]
        r_mc = cv2.Rodrigues(rm_rv)[0]
        # marker -> camera -> world
        r_mw = r_wc.T @ r_mc
        centre = r_wc.T @ (rm_tv.ravel() - tv.ravel())
        yaw = math.degrees(math.atan2(r_mw[1, 0], r_mw[0, 0]))
        x, y, phi = rm.robot_pose(centre[0], centre[1], yaw)
        rows.append((x, y, (phi + 180.0) % 360.0 - 180.0))

    info, stamps = scan(path, per_frame)
    timing = frame_times(stamps, info.fps_nominal, fps, str(path))
    pose = np.array(rows, dtype=float).reshape(-1, 3)
    f = np.isfinite(pose).all(axis=1)
    if f.any():
        pose[f, 2] = np.degrees(np.unwrap(np.radians(pose[f, 2])))
    return timing.t_s, pose


def pose_errors(t_s: np.ndarray, pose: np.ndarray, truth_pose: np.ndarray) -> dict[str, float]:
    """RMS and median position [m] and heading [deg] error of measured against true poses at
    the same frames (frames without a measurement left out), and the share of frames measured."""
    f = np.isfinite(pose).all(axis=1)
    if not f.any():
        return {"position_rmse_m": math.nan, "heading_rmse_deg": math.nan, "found_share": 0.0}
    dp = pose[f, :2] - truth_pose[f, :2]
    dphi = (pose[f, 2] - truth_pose[f, 2] + 180.0) % 360.0 - 180.0
    dist = np.sqrt(np.sum(dp ** 2, axis=1))
    return {"position_rmse_m": float(np.sqrt(np.mean(dist ** 2))),
            "heading_rmse_deg": float(np.sqrt(np.mean(dphi ** 2))),
            "position_median_m": float(np.median(dist)),
            "heading_median_deg": float(np.median(np.abs(dphi))),
            "found_share": float(f.mean()), "frames": len(t_s)}


#: Columns of ``POSE.csv``.
POSE_CSV_COLUMNS = ("t_s", "x_m", "y_m", "phi_deg")


def write_pose_csv(path: str | Path, t_s: np.ndarray, pose: np.ndarray) -> Path:
    """Write ``POSE.csv`` (``t_s, x_m, y_m, phi_deg``; empty cells where nothing was measured),
    atomically (a temporary file renamed into place)."""
    import csv
    import os

    from ..errors import RecordingError
    from ..io.recording import format_value

    p = Path(path)
    tmp = p.with_name(p.name + ".tmp")
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        with tmp.open("w", newline="") as fh:
            w = csv.writer(fh, lineterminator="\n")
            w.writerow(POSE_CSV_COLUMNS)
            for t, row in zip(t_s, pose, strict=True):
                w.writerow([format_value(float(t))] + [format_value(float(v)) for v in row])
        os.replace(tmp, p)
    except OSError as err:
        raise RecordingError(f"{p}: cannot write: {err.strerror or err}") from err
    return p
