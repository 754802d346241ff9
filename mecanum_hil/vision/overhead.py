"""Render an overhead camera's view of the robot driving as a recording's pose says.

For tests and the demo of ``measure-pose``: a static camera above the floor, looking down
obliquely through a lens with distortion, sees markers lying on the floor and the robot, a box
whose top carries its marker (offset from the centre, turned, at the box's height). The picture
is computed by ray casting through the lens: every pixel's ray (OpenCV's distortion model,
inverted to convergence) is intersected with the floor and with the plane of the robot's top,
so the marker's corners are where :meth:`CameraModel.project` puts them. Each pixel averages
``supersample x supersample`` rays (anti-aliasing, so the truth is sub-pixel). The truth is the
recording's pose, linear between its samples (heading unwrapped), at the frame times.

Not modelled: motion blur (a short exposure is assumed), shadows, perspective of the box's
sides beyond its silhouette (drawn in one shade).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import VideoError
from ..io.recording import Recording
from .camera import CameraModel, CameraPose, look_at
from .render import check_frame, check_noise, check_seed, check_times, schedule_frames
from .scene import FloorMarker, RobotMarker, Scene, dictionary_by_name, marker_corners_xy
from .video import VideoWriter, fourcc_for

_TEXEL_M = 0.0015  # robot-top texture resolution: well below a pixel's footprint


@dataclass(frozen=True)
class OverheadSettings:
    """The overhead camera, the scene and the picture's imperfections.

    Attributes
    ----------
    width_px, height_px : int
        Frame size [px], 160x120 .. 4096x2160
        (:func:`~mecanum_hil.vision.render.check_frame`).
    fps : float
        Frame rate [1/s], 0.1 .. :data:`~mecanum_hil.vision.render.MAX_RENDER_FPS`.
    camera_start_s : float
        Recording time of the first frame after the recording's first sample [s], >= 0.
    duration_s : float or None
        Video length [s]; default: to the recording's end (a video running past it is
        refused).
    tilt_deg : float
        Angle of the view axis from straight down [deg] (oblique view).
    azimuth_deg : float or None
        Direction the camera looks in, from world X counter-clockwise [deg]; default: so that
        the longer side of the robot's path runs along the image's width.
    roll_deg : float
        Rotation of the image about the view axis [deg].
    hfov_deg : float
        Horizontal field of view of the undistorted lens [deg].
    distortion : tuple of 5 float
        OpenCV's ``(k1, k2, p1, p2, k3)``, finite.
    principal_offset : (float, float)
        Principal point off the image centre, as shares of width and height.
    noise_std : float
        Sensor noise, standard deviation [grey levels], 0..255.
    jpeg_quality : int or None
        Extra JPEG compression of each frame (1..100).
    dictionary : str
        Marker dictionary (OpenCV name).
    robot_marker_id, robot_marker_size_m, marker_height_m : int, float, float
        The robot's marker, its black square's side [m] and its plane's height [m] (the top of
        the box).
    marker_forward_m, marker_left_m, marker_yaw_deg : float
        Its centre in the robot frame [m] and its yaw from the robot's forward axis [deg].
    body_length_m, body_width_m : float
        The box [m].
    floor_marker_size_m : float
        Side of the eight floor markers [m], placed around the robot's path.
    occlusions_s : tuple of (start, end)
        Video-time intervals [s] when a card hides the robot's marker.
    supersample : int
        Rays per pixel along each axis.
    seed : int
        Seed of the noise, 0 .. :data:`~mecanum_hil.vision.render.MAX_SEED`.
    """

    width_px: int = 1280
    height_px: int = 720
    fps: float = 30.0
    camera_start_s: float = 0.0
    duration_s: float | None = None
    tilt_deg: float = 25.0
    azimuth_deg: float | None = None
    roll_deg: float = 4.0
    hfov_deg: float = 75.0
    distortion: tuple[float, float, float, float, float] = (-0.20, 0.06, 0.0008, -0.0005, 0.0)
    principal_offset: tuple[float, float] = (0.012, -0.009)
    noise_std: float = 2.0
    jpeg_quality: int | None = None
    dictionary: str = "DICT_4X4_50"
    robot_marker_id: int = 0
    robot_marker_size_m: float = 0.2
    marker_height_m: float = 0.23
    marker_forward_m: float = 0.18
    marker_left_m: float = 0.1
    marker_yaw_deg: float = -70.0
    body_length_m: float = 0.977
    body_width_m: float = 0.775
    floor_marker_size_m: float = 0.25
    occlusions_s: tuple[tuple[float, float], ...] = ()
    supersample: int = 3
    seed: int = 0

    def __post_init__(self) -> None:
        check_frame(self.width_px, self.height_px, self.fps, 160, 120)
        check_times(self.camera_start_s, self.duration_s)
        check_noise(self.noise_std)
        check_seed(self.seed)
        if len(self.distortion) != 5 or not all(math.isfinite(v) for v in self.distortion):
            raise VideoError("distortion (--distortion) must be five finite numbers "
                             "k1,k2,p1,p2,k3, got "
                             f"{','.join(f'{v:g}' for v in self.distortion)}")
        for name in ("roll_deg", "principal_offset", "azimuth_deg"):
            value = getattr(self, name)
            if value is not None and not np.isfinite(np.asarray(value, dtype=float)).all():
                raise VideoError(f"{name} must be finite, got {value}")
        if not 0.0 <= self.tilt_deg <= 60.0:
            raise VideoError(f"camera tilt must be within 0..60 deg, got {self.tilt_deg}")
        if not 20.0 <= self.hfov_deg <= 120.0:
            raise VideoError(f"field of view must be within 20..120 deg, got {self.hfov_deg}")
        if self.jpeg_quality is not None and not 1 <= self.jpeg_quality <= 100:
            raise VideoError(f"JPEG quality must be within 1..100, got {self.jpeg_quality}")
        if not 1 <= self.supersample <= 8:
            raise VideoError("supersample must be within 1..8")
        if self.robot_marker_size_m * 1.3 > min(self.body_length_m, self.body_width_m):
            raise VideoError("the robot's marker does not fit on its top")

    @property
    def robot_marker(self) -> RobotMarker:
        """The robot's marker as ``scene.toml`` describes it."""
        return RobotMarker(self.robot_marker_id, self.robot_marker_size_m, self.marker_height_m,
                           self.marker_forward_m, self.marker_left_m, self.marker_yaw_deg)


@dataclass(frozen=True)
class OverheadResult:
    """A rendered overhead video and its truth.

    Attributes
    ----------
    path : Path
    frame_t_s : ndarray, shape (N,)
        Video time of each frame [s].
    recording_t_s : ndarray, shape (N,)
        Recording time of each frame [s].
    pose : ndarray, shape (N, 3)
        True robot pose ``(X [m], Y [m], phi [deg])`` at each frame (phi unwrapped).
    marker_visible : ndarray of bool, shape (N,)
        Whether the robot's marker is wholly in the picture and not hidden by a card.
    camera : CameraModel
    camera_pose : CameraPose
    scene : Scene
    settings : OverheadSettings
    """

    path: Path
    frame_t_s: np.ndarray
    recording_t_s: np.ndarray
    pose: np.ndarray
    marker_visible: np.ndarray
    camera: CameraModel
    camera_pose: CameraPose
    scene: Scene
    settings: OverheadSettings


def pose_truth(rec: Recording, t_rec_s: np.ndarray) -> np.ndarray:
    """The recording's pose at recording times, linear between samples with a pose (heading
    unwrapped), held outside [m, m, deg]."""
    ok = np.isfinite(rec.pose).all(axis=1)
    if ok.sum() < 2:
        raise VideoError("the recording has no pose columns to render (make one with "
                         "`mecanum-hil simulate` or `campaign --pose-noise 0,0,0`)")
    t = rec.t_s[ok]
    p = rec.pose[ok]
    phi = np.degrees(np.unwrap(np.radians(p[:, 2])))
    return np.column_stack([np.interp(t_rec_s, t, p[:, 0]), np.interp(t_rec_s, t, p[:, 1]),
                            np.interp(t_rec_s, t, phi)])


def frame_schedule(rec: Recording, settings: OverheadSettings) -> tuple[np.ndarray, np.ndarray]:
    """Video times and recording times of the frames [s]
    (:func:`~mecanum_hil.vision.render.schedule_frames`)."""
    return schedule_frames(rec.t_s, settings.camera_start_s, settings.duration_s, settings.fps)


def _body_corners(pose: np.ndarray, s: OverheadSettings) -> np.ndarray:
    """The box's 8 corners [m] for each pose, shape (N, 8, 3)."""
    hl, hw = 0.5 * s.body_length_m, 0.5 * s.body_width_m
    local = np.array([[hl, hw], [hl, -hw], [-hl, -hw], [-hl, hw]])
    phi = np.radians(pose[:, 2])
    c, sn = np.cos(phi)[:, None], np.sin(phi)[:, None]
    x = pose[:, 0:1] + c * local[:, 0] - sn * local[:, 1]
    y = pose[:, 1:2] + sn * local[:, 0] + c * local[:, 1]
    n = len(pose)
    out = np.empty((n, 8, 3))
    out[:, :4, 0] = out[:, 4:, 0] = x
    out[:, :4, 1] = out[:, 4:, 1] = y
    out[:, :4, 2] = 0.0
    out[:, 4:, 2] = s.marker_height_m
    return out


def plan_scene(pose: np.ndarray, s: OverheadSettings) -> tuple[CameraModel, CameraPose, Scene]:
    """Camera and floor markers for a path: eight markers around it, the camera aimed at its
    centre and as close as keeps the robot and every marker in the picture."""
    corners = _body_corners(pose, s).reshape(-1, 3)
    lo, hi = corners[:, :2].min(axis=0), corners[:, :2].max(axis=0)
    margin = 0.3 + 0.5 * s.floor_marker_size_m
    lo, hi = lo - margin, hi + margin
    mid = 0.5 * (lo + hi)
    floor = []
    spots = [(lo[0], lo[1]), (mid[0], lo[1]), (hi[0], lo[1]), (hi[0], mid[1]),
             (hi[0], hi[1]), (mid[0], hi[1]), (lo[0], hi[1]), (lo[0], mid[1])]
    for k, (x, y) in enumerate(spots):
        floor.append(FloorMarker(s.robot_marker_id + 1 + k, float(x), float(y),
                                 s.floor_marker_size_m, float((17.0 + 41.0 * k) % 360.0)))
    scene = Scene(s.dictionary, tuple(floor), s.robot_marker)
    w, h = s.width_px, s.height_px
    fx = 0.5 * w / math.tan(math.radians(0.5 * s.hfov_deg))
    camera = CameraModel(w, h, fx, fx, 0.5 * (w - 1) + s.principal_offset[0] * w,
                         0.5 * (h - 1) + s.principal_offset[1] * h, tuple(s.distortion))
    span = hi - lo
    az = s.azimuth_deg
    if az is None:  # the image is wider than tall: put the path's longer side along it
        az = 90.0 if span[0] >= span[1] else 0.0
    a, t = math.radians(az), math.radians(s.tilt_deg)
    view = np.array([math.sin(t) * math.cos(a), math.sin(t) * math.sin(a), -math.cos(t)])
    up = np.array([math.cos(a), math.sin(a), 0.0])
    up = math.cos(math.radians(s.roll_deg)) * up + math.sin(math.radians(s.roll_deg)) * \
        np.cross(view, up)
    target = np.array([mid[0], mid[1], 0.0])
    need = np.vstack([corners, np.concatenate([m.corners_m() for m in floor])])
    border = 0.04 * min(w, h)

    def fits(dist: float) -> bool:
        pose_c = look_at(target - dist * view, target, up)
        pc = (need - pose_c.position_m) @ pose_c.rotation.T
        if (pc[:, 2] < 0.05).any():
            return False
        r = np.hypot(pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2])
        if r.max() > 1.4 * math.tan(math.radians(0.5 * s.hfov_deg)):
            return False  # beyond where the distortion polynomial is meant to hold
        img = camera.project(need, pose_c)
        return bool((img[:, 0] > border).all() and (img[:, 0] < w - 1 - border).all()
                    and (img[:, 1] > border).all() and (img[:, 1] < h - 1 - border).all())

    near, far = 0.5, 50.0
    if not fits(far):
        raise VideoError("the robot's path does not fit in the picture at any distance "
                         "(check --tilt and --distortion)")
    for _ in range(40):
        mid_d = math.sqrt(near * far)
        near, far = (near, mid_d) if fits(mid_d) else (mid_d, far)
    return camera, look_at(target - far * view, target, up), scene


def _marker_bits(dictionary, marker_id: int) -> np.ndarray:
    """The marker's cells including its black border, 1 = white, shape (k, k)."""
    import cv2

    side = dictionary.markerSize + 2
    img = cv2.aruco.generateImageMarker(dictionary, int(marker_id), side * 10, borderBits=1)
    return (img[5::10, 5::10] > 127).astype(np.float32)


def _sample_marker(bits: np.ndarray, mx: np.ndarray, my: np.ndarray, size_m: float,
                   quiet: float) -> tuple[np.ndarray, np.ndarray]:
    """Grey level (0..1) and coverage of a printed marker (white paper ``quiet`` x the black
    square) at marker-frame points [m]."""
    k = bits.shape[0]
    u = mx / size_m + 0.5  # 0..1 across the black square, left to right
    v = 0.5 - my / size_m  # 0..1 top to bottom
    inside = (u >= 0) & (u < 1) & (v >= 0) & (v < 1)
    col = np.clip((u * k).astype(int), 0, k - 1)
    row = np.clip((v * k).astype(int), 0, k - 1)
    grey = np.where(inside, bits[row, col], 1.0)
    half = 0.5 * quiet
    paper = (np.abs(mx) <= half * size_m) & (np.abs(my) <= half * size_m)
    return grey, paper


class _Renderer:
    """Static parts of the picture (floor, markers, per-pixel rays) and one frame's drawing."""

    def __init__(self, s: OverheadSettings, camera: CameraModel, pose_c: CameraPose,
                 scene: Scene) -> None:
        self.s, self.camera, self.pose_c, self.scene = s, camera, pose_c, scene
        w, h = s.width_px, s.height_px
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
        n = camera.normalised(np.column_stack([xx.ravel(), yy.ravel()])).reshape(h, w, 2)
        # the rays of sub-pixel samples, from the map's local derivatives (it is smooth)
        self.n = n
        self.dn_du = np.gradient(n, axis=1)
        self.dn_dv = np.gradient(n, axis=0)
        k = s.supersample
        self.offsets = [((i + 0.5) / k - 0.5, (j + 0.5) / k - 0.5)
                        for i in range(k) for j in range(k)]
        self.rot = pose_c.rotation
        self.centre = pose_c.position_m
        self.dictionary = dictionary_by_name(scene.dictionary)
        self.background = self._floor()
        self.top_texture = self._top_texture()

    def _plane_xy(self, region: tuple[slice, slice], du: float, dv: float, height_m: float
                  ) -> tuple[np.ndarray, np.ndarray]:
        n = self.n[region] + du * self.dn_du[region] + dv * self.dn_dv[region]
        r = self.rot
        dx = r[0, 0] * n[..., 0] + r[1, 0] * n[..., 1] + r[2, 0]
        dy = r[0, 1] * n[..., 0] + r[1, 1] * n[..., 1] + r[2, 1]
        dz = r[0, 2] * n[..., 0] + r[1, 2] * n[..., 1] + r[2, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (height_m - self.centre[2]) / dz
        t = np.where(t > 0, t, np.nan)
        return self.centre[0] + t * dx, self.centre[1] + t * dy

    def _floor(self) -> np.ndarray:
        s = self.s
        h, w = s.height_px, s.width_px
        x, y = self._plane_xy((slice(None), slice(None)), 0.0, 0.0, 0.0)
        # a dull, slowly varying floor (concrete-like), never mistaken for a marker
        grey = 105.0 + 12.0 * np.sin(1.3 * x + 0.4) * np.cos(0.9 * y) + 6.0 * np.sin(3.1 * y)
        grey = np.where(np.isfinite(grey), grey, 60.0)
        for m in self.scene.floor:
            box = self.camera.project(
                np.column_stack([marker_corners_xy(m.x_m, m.y_m, 1.6 * m.size_m, m.yaw_deg),
                                 np.zeros(4)]), self.pose_c)
            x0, y0 = np.floor(box.min(axis=0)).astype(int) - 2
            x1, y1 = np.ceil(box.max(axis=0)).astype(int) + 3
            x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
            if x1 <= x0 or y1 <= y0:
                continue
            reg = (slice(y0, y1), slice(x0, x1))
            bits = _marker_bits(self.dictionary, m.id)
            a = math.radians(m.yaw_deg)
            acc = np.zeros((y1 - y0, x1 - x0))
            for du, dv in self.offsets:
                px, py = self._plane_xy(reg, du, dv, 0.0)
                ex, ey = px - m.x_m, py - m.y_m
                mx = math.cos(a) * ex + math.sin(a) * ey
                my = -math.sin(a) * ex + math.cos(a) * ey
                g, paper = _sample_marker(bits, mx, my, m.size_m, 1.5)
                acc += np.where(paper, 25.0 + 200.0 * g, grey[reg])
            grey[reg] = acc / len(self.offsets)
        return grey.astype(np.float32)

    def _top_texture(self) -> np.ndarray:
        """The robot's top in its own frame: premultiplied grey and coverage, texel
        ``_TEXEL_M``, rows from left (+y) to right, columns from back to front."""
        s = self.s
        rm = self.scene.robot
        nx = math.ceil(s.body_length_m / _TEXEL_M)
        ny = math.ceil(s.body_width_m / _TEXEL_M)
        sub = 4
        acc = np.zeros((ny, nx), np.float32)
        cov = np.zeros((ny, nx), np.float32)
        bits = _marker_bits(self.dictionary, rm.marker_id)
        a = math.radians(rm.yaw_deg)
        cols = np.arange(nx)
        rows = np.arange(ny)
        for i in range(sub):
            for j in range(sub):
                u = -0.5 * s.body_length_m + (cols + (i + 0.5) / sub) * _TEXEL_M
                v = 0.5 * s.body_width_m - (rows + (j + 0.5) / sub) * _TEXEL_M
                uu, vv = np.meshgrid(u, v)
                on = (np.abs(uu) <= 0.5 * s.body_length_m) & (np.abs(vv) <= 0.5 * s.body_width_m)
                ex, ey = uu - rm.forward_m, vv - rm.left_m
                mx = math.cos(a) * ex + math.sin(a) * ey
                my = -math.sin(a) * ex + math.cos(a) * ey
                g, paper = _sample_marker(bits, mx, my, rm.size_m, 1.5)
                # the top: a light grey plate with a darker rim, the marker on white paper
                rim = (np.abs(uu) > 0.5 * s.body_length_m - 0.03) | \
                    (np.abs(vv) > 0.5 * s.body_width_m - 0.03)
                plate = np.where(rim, 95.0, 150.0)
                acc += np.where(on, np.where(paper, 25.0 + 210.0 * g, plate), 0.0)
                cov += on
        return np.dstack([acc / sub ** 2, cov / sub ** 2]).astype(np.float32)

    def draw(self, t_video_s: float, pose: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        import cv2

        s = self.s
        h, w = s.height_px, s.width_px
        frame = self.background.copy()
        corners = _body_corners(pose[None, :], s)[0]
        # the box's silhouette (its sides), its edges sampled densely because the lens bends them
        edges = [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4),
                 (0, 4), (1, 5), (2, 6), (3, 7)]
        lin = np.linspace(0.0, 1.0, 12)[:, None]
        pts = np.concatenate([corners[a] + lin * (corners[b] - corners[a]) for a, b in edges])
        img = self.camera.project(pts, self.pose_c)
        hull = cv2.convexHull(np.round(img * 16).astype(np.int32))
        cv2.fillConvexPoly(frame, hull, 55.0, cv2.LINE_AA, 4)
        x0, y0 = np.floor(img.min(axis=0)).astype(int) - 2
        x1, y1 = np.ceil(img.max(axis=0)).astype(int) + 3
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
        if x1 > x0 and y1 > y0:
            reg = (slice(y0, y1), slice(x0, x1))
            phi = math.radians(pose[2])
            c, sn = math.cos(phi), math.sin(phi)
            tex = self.top_texture
            acc = np.zeros((y1 - y0, x1 - x0, 2), np.float32)
            for du, dv in self.offsets:
                px, py = self._plane_xy(reg, du, dv, s.marker_height_m)
                ex, ey = px - pose[0], py - pose[1]
                u = c * ex + sn * ey
                v = -sn * ex + c * ey
                map_x = ((u + 0.5 * s.body_length_m) / _TEXEL_M - 0.5).astype(np.float32)
                map_y = ((0.5 * s.body_width_m - v) / _TEXEL_M - 0.5).astype(np.float32)
                acc += cv2.remap(tex, np.nan_to_num(map_x, nan=-10.0),
                                 np.nan_to_num(map_y, nan=-10.0), cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            acc /= len(self.offsets)
            frame[reg] = frame[reg] * (1.0 - acc[..., 1]) + acc[..., 0]
        if any(a <= t_video_s <= b for a, b in s.occlusions_s):
            mx, my, myaw = self.scene.robot.marker_pose(pose[0], pose[1], pose[2])
            card = marker_corners_xy(mx, my, 2.2 * self.scene.robot.size_m, myaw + 10.0)
            cimg = self.camera.project(np.column_stack(
                [card, np.full(4, s.marker_height_m + 0.1)]), self.pose_c)
            cv2.fillConvexPoly(frame, np.round(cimg * 16).astype(np.int32), 140.0,
                               cv2.LINE_AA, 4)
        if s.noise_std > 0:
            frame += rng.standard_normal(frame.shape, dtype=np.float32) * np.float32(s.noise_std)
        grey = np.clip(frame + 0.5, 0, 255).astype(np.uint8)
        # a faintly tinted colour picture (a camera is not grey), the grey level carries it
        out = cv2.merge([grey, grey, cv2.add(grey, 3)])
        if s.jpeg_quality is not None:
            ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(s.jpeg_quality)])
            if ok:
                out = cv2.imdecode(buf, cv2.IMREAD_COLOR)
        return out


def marker_visible(pose: np.ndarray, camera: CameraModel, camera_pose: CameraPose,
                   scene: Scene, t_video_s: np.ndarray,
                   occlusions_s: tuple[tuple[float, float], ...] = ()) -> np.ndarray:
    """Whether the robot's marker is wholly inside the picture (2 px margin) and not behind a
    card, per pose."""
    rm = scene.robot
    mx, my, myaw = rm.marker_pose(pose[:, 0], pose[:, 1], pose[:, 2])
    out = np.zeros(len(pose), bool)
    w, h = camera.width_px, camera.height_px
    for i in range(len(pose)):
        xy = marker_corners_xy(mx[i], my[i], rm.size_m, myaw[i])
        img = camera.project(np.column_stack([xy, np.full(4, rm.height_m)]), camera_pose)
        out[i] = bool((img[:, 0] > 2).all() and (img[:, 0] < w - 3).all()
                      and (img[:, 1] > 2).all() and (img[:, 1] < h - 3).all())
        if any(a <= t_video_s[i] <= b for a, b in occlusions_s):
            out[i] = False
    return out


def render_overhead_frames(rec: Recording, settings: OverheadSettings
                           ) -> tuple[OverheadResult, Iterator[np.ndarray]]:
    """The truth (path left empty) and an iterator over the frames (BGR uint8)."""
    tv, tr = frame_schedule(rec, settings)
    pose = pose_truth(rec, tr)
    camera, pose_c, scene = plan_scene(pose, settings)
    visible = marker_visible(pose, camera, pose_c, scene, tv, settings.occlusions_s)
    result = OverheadResult(Path(), tv, tr, pose, visible, camera, pose_c, scene, settings)

    def frames() -> Iterator[np.ndarray]:
        renderer = _Renderer(settings, camera, pose_c, scene)
        rng = np.random.default_rng(settings.seed)
        for i in range(tv.size):
            yield renderer.draw(float(tv[i]), pose[i], rng)

    return result, frames()


def render_overhead(rec: Recording, path: str | Path, settings: OverheadSettings | None = None,
                    progress=None) -> OverheadResult:
    """Render the overhead view of a recording's pose to a video file and return the truth.

    Parameters
    ----------
    rec : Recording
        Needs its pose columns.
    path : str or Path
        ``.mp4`` (mp4v) or ``.avi`` (MJPG).
    settings : OverheadSettings, optional
    progress : callable, optional
        Called as ``progress(done, total)`` after each frame.
    """
    from dataclasses import replace

    s = settings or OverheadSettings()
    fourcc_for(path)
    result, frames = render_overhead_frames(rec, s)
    with VideoWriter(path, s.fps, (s.width_px, s.height_px)) as writer:
        for i, frame in enumerate(frames):
            writer.write(frame)
            if progress is not None:
                progress(i + 1, result.frame_t_s.size)
    return replace(result, path=Path(path))
