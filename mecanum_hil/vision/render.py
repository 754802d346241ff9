"""Render a video of wheels with markers turning as a recording's wheel speeds say.

The renderer exists for tests and the demo: it gives videos with a known truth. Each wheel is a
dark tyre, a grey hub and grey spokes (unsaturated, so they never pass for a marker) with one
saturated dot near the rim. The wheel angle is the exact integral of the recording's wheel speed
(taken as piecewise linear between samples) at each frame's mid-exposure time. Realism knobs:
sensor noise, motion blur (the dot is smeared over the exposure), lighting drift, mains flicker,
a marker colour shifting under the light, an oblique view (an affine squash: the rim becomes an
ellipse), JPEG compression of each frame on top of the codec's, distractor objects (static and
moving saturated blobs), a fender hiding the top of each wheel, cards hiding the wheels for a
while, and a camera that shakes and drifts. The truth kept beside each video: the wheel speeds
and angles, the camera's offset and the share of each marker in view at every frame.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import VideoError
from ..io.recording import WHEEL_COLUMNS, Recording
from .video import MIN_FPS, VideoWriter, fourcc_for

_SHIFT = 4  # cv2 drawing with 1/16 px coordinates, so the truth is sub-pixel
_SCALE = 1 << _SHIFT

#: Largest frame side [px] and frame area [px] a renderer draws (DCI 4K, 4096 x 2160): every
#: frame is drawn in memory at several bytes a pixel (the overhead renderer keeps rays of every
#: pixel), so a typing error such as 100000x100000 is refused before anything is allocated.
MAX_FRAME_SIDE_PX = 4096
MAX_FRAME_AREA_PX = 4096 * 2160
#: Highest frame rate a renderer writes [1/s]: every frame is drawn, so beyond a high-speed
#: camera's rate the number is a typing error (MPEG-4's clock also ends at 65535 ticks/s).
MAX_RENDER_FPS = 1000.0
#: Most distractor objects drawn beside the wheels.
MAX_DISTRACTORS = 100
#: Largest seed (OpenCV's random generator takes a C int).
MAX_SEED = 2 ** 31 - 1


@dataclass(frozen=True)
class RenderSettings:
    """How to film the wheels.

    Attributes
    ----------
    width_px, height_px : int
        Frame size [px], 64x48 .. 4096x2160 (:func:`check_frame`).
    fps : float
        Frame rate [1/s], 0.1 .. :data:`MAX_RENDER_FPS`.
    wheels : tuple of int
        Wheels (1..4) to show, side by side, each with its own marker hue.
    camera_start_s : float
        Recording time of the first frame, after the recording's first sample [s] (>= 0); the
        video clock starts at 0 there (the offset ``measure-video --recording`` must find).
    duration_s : float or None
        Video length [s]; default: until the recording ends. A video running past the
        recording's end is refused (its length is bounded by the recording).
    marker_hues_deg : tuple of float
        Hue of each wheel's marker [deg] (OpenCV hue x 2), cycled.
    mirror : bool
        Film the wheels from the other side: positive wheel speed turns clockwise in the image.
    noise_std : float
        Sensor noise, standard deviation [grey levels of 255], 0..255.
    exposure : float
        Shutter open for this fraction of the frame interval (0: no motion blur).
    lighting_drift : float
        Relative amplitude of a slow brightness change (0.2: +-20 %), below 1.
    tilt_deg : float
        Oblique view: angle between the wheel axis and the camera axis [deg].
    tilt_axis_deg : float
        Direction in the image of the axis the wheel is tilted about [deg].
    jpeg_quality : int or None
        Extra JPEG compression of each frame (1..100), on top of the codec's.
    distractors : int
        Saturated objects off the wheels: every second one moves on a straight line (at most
        :data:`MAX_DISTRACTORS`).
    occlusions_s : tuple of (start, end)
        Video-time intervals [s] when a grey card hides the wheels.
    fender : float
        Share of each wheel's height, from the top, hidden by a fender (0: none; 0.4 hides the
        marker over about a third of each turn).
    shake_px : float
        Camera shake: standard deviation of a random offset of each frame, per axis [px] (at
        most the frame's smaller side).
    drift_px : float
        Camera drift: amplitude of a slow wandering of the view (periods 7 s and 11 s) [px]
        (at most the frame's smaller side).
    flicker : float
        Relative amplitude of mains-light flicker at ``flicker_hz`` (integrated over the
        exposure, so it beats with the frame rate).
    flicker_hz : float
        Flicker frequency [Hz] (twice the mains frequency: 100 or 120).
    hue_shift_deg : float
        The marker's colour drifting under the light: amplitude of a slow hue rotation (period
        5 s) of every saturated colour in the picture [deg], 0..180.
    seed : int
        Seed of the noise and of the distractors' placement, 0 .. :data:`MAX_SEED`.
    marker : str
        ``"dot"`` (a saturated dot near the rim) or ``"aruco"`` (ArUco marker id ``k`` of
        :data:`~mecanum_hil.vision.aruco.DICTIONARY` on the hub of the k-th shown wheel).
    """

    width_px: int = 320
    height_px: int = 240
    fps: float = 30.0
    wheels: tuple[int, ...] = (1,)
    camera_start_s: float = 0.0
    duration_s: float | None = None
    marker_hues_deg: tuple[float, ...] = (120.0, 0.0, 240.0, 60.0)
    mirror: bool = False
    noise_std: float = 0.0
    exposure: float = 0.0
    lighting_drift: float = 0.0
    tilt_deg: float = 0.0
    tilt_axis_deg: float = 0.0
    jpeg_quality: int | None = None
    distractors: int = 0
    occlusions_s: tuple[tuple[float, float], ...] = ()
    seed: int = 0
    marker: str = "dot"
    fender: float = 0.0
    shake_px: float = 0.0
    drift_px: float = 0.0
    flicker: float = 0.0
    flicker_hz: float = 100.0
    hue_shift_deg: float = 0.0

    def __post_init__(self) -> None:
        check_frame(self.width_px, self.height_px, self.fps, 64, 48)
        check_times(self.camera_start_s, self.duration_s)
        if not self.wheels or any(w not in (1, 2, 3, 4) for w in self.wheels):
            raise VideoError(f"wheels must be numbers 1..4, got {self.wheels}")
        if not 0.0 <= self.exposure <= 1.0:
            raise VideoError(f"exposure (--blur) must be within 0..1, got {self.exposure}")
        if not 0.0 <= self.tilt_deg < 80.0:
            raise VideoError(f"tilt must be within 0..80 deg, got {self.tilt_deg}")
        if not math.isfinite(self.tilt_axis_deg):
            raise VideoError(f"tilt axis (--tilt-axis) must be a finite angle [deg], got "
                             f"{self.tilt_axis_deg}")
        if self.marker not in ("dot", "aruco"):
            raise VideoError(f"marker must be 'dot' or 'aruco', got '{self.marker}'")
        if self.jpeg_quality is not None and not 1 <= self.jpeg_quality <= 100:
            raise VideoError(f"JPEG quality must be within 1..100, got {self.jpeg_quality}")
        if not 0.0 <= self.fender < 1.0:
            raise VideoError(f"fender must be within 0..1 (share of the wheel), got {self.fender}")
        check_noise(self.noise_std)
        if not 0.0 <= self.lighting_drift < 1.0:
            raise VideoError("lighting drift (--lighting-drift) must be within 0..1 (a relative "
                             f"amplitude below 100 %), got {self.lighting_drift}")
        if not 0 <= self.distractors <= MAX_DISTRACTORS:
            raise VideoError(f"distractors (--distractors) must be within "
                             f"0..{MAX_DISTRACTORS}, got {self.distractors}")
        check_seed(self.seed)
        for name in ("shake_px", "drift_px", "flicker", "hue_shift_deg"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0.0):
                raise VideoError(f"{name} must be >= 0, got {getattr(self, name)}")
        side = min(self.width_px, self.height_px)
        for name, flag in (("shake_px", "--shake"), ("drift_px", "--drift")):
            if getattr(self, name) > side:
                raise VideoError(f"{name} ({flag}) must be at most the frame's smaller side "
                                 f"({side} px), got {getattr(self, name):g}")
        if self.flicker >= 1.0 or not (self.flicker_hz > 0 and math.isfinite(self.flicker_hz)):
            raise VideoError("flicker (--flicker) must be below 1 and its frequency (--flicker-hz) "
                             "a finite number > 0 Hz")
        if self.hue_shift_deg > 180.0:
            raise VideoError(f"hue_shift_deg (--hue-shift) must be within 0..180 deg, got "
                             f"{self.hue_shift_deg:g}")
        for t0, t1 in self.occlusions_s:
            if not t1 > t0:
                raise VideoError(f"occlusion ({t0}, {t1}): the end must come after the start")


def check_frame(width_px: int, height_px: int, fps: float, min_width_px: int,
                min_height_px: int) -> None:
    """Refuse a frame size or rate a renderer cannot or should not write, before anything is
    allocated or a video writer opened.

    Parameters
    ----------
    width_px, height_px : int
        Frame size [px]: at least ``min_width_px x min_height_px``, at most
        :data:`MAX_FRAME_SIDE_PX` a side and :data:`MAX_FRAME_AREA_PX` in all.
    fps : float
        Frame rate [1/s], within :data:`~mecanum_hil.vision.video.MIN_FPS` ..
        :data:`MAX_RENDER_FPS`.
    min_width_px, min_height_px : int
        Smallest frame the renderer draws [px].

    Raises
    ------
    VideoError
        One line naming the bound.
    """
    if width_px < min_width_px or height_px < min_height_px:
        raise VideoError(f"frame size (--size) must be at least {min_width_px}x{min_height_px} "
                         f"px, got {width_px}x{height_px}")
    if max(width_px, height_px) > MAX_FRAME_SIDE_PX or \
            width_px * height_px > MAX_FRAME_AREA_PX:
        raise VideoError(f"frame size (--size) must be at most {MAX_FRAME_SIDE_PX} px a side "
                         f"and {MAX_FRAME_AREA_PX} px in all (4096x2160), got "
                         f"{width_px}x{height_px}")
    if not MIN_FPS <= fps <= MAX_RENDER_FPS:
        raise VideoError(f"--fps must be within {MIN_FPS:g} .. {MAX_RENDER_FPS:g} frames per "
                         f"second, got {fps:g}")


def check_times(camera_start_s: float, duration_s: float | None) -> None:
    """Refuse a camera start [s] that is negative or not finite, and a video length [s] that is
    not a finite number > 0 (the recording's own length bounds it later, see
    :func:`schedule_frames`)."""
    if not (math.isfinite(camera_start_s) and camera_start_s >= 0.0):
        raise VideoError(f"--start must be a finite number of seconds >= 0, got "
                         f"{camera_start_s:g}")
    if duration_s is not None and not (math.isfinite(duration_s) and duration_s > 0):
        raise VideoError(f"--duration must be > 0 s and finite, got {duration_s:g}")


def check_noise(noise_std: float) -> None:
    """Refuse a sensor noise [grey levels] that is negative, beyond 255 or not finite."""
    if not 0.0 <= noise_std <= 255.0:
        raise VideoError(f"noise (--noise) must be within 0..255 grey levels, got {noise_std:g}")


def check_seed(seed: int) -> None:
    """Refuse a seed outside 0 .. :data:`MAX_SEED`."""
    if not 0 <= seed <= MAX_SEED:
        raise VideoError(f"--seed must be within 0..{MAX_SEED}, got {seed}")


@dataclass(frozen=True)
class WheelPlacement:
    """Where a wheel is drawn: centre ``(cx_px, cy_px)``, rim radius, and its ROI."""

    wheel: int
    cx_px: float
    cy_px: float
    radius_px: float
    roi: tuple[int, int, int, int]


@dataclass(frozen=True)
class RenderResult:
    """A rendered video and its truth.

    Attributes
    ----------
    path : Path
    frame_t_s : ndarray, shape (N,)
        Video time of each frame [s] (0 at the first frame).
    recording_t_s : ndarray, shape (N,)
        Recording time of each frame [s].
    wheel_rpm : ndarray, shape (N, W)
        True speed of each shown wheel at each frame [rpm].
    angle_turns : ndarray, shape (N, W)
        True wheel angle, as the recording's sign convention counts it [turns].
    placements : tuple of WheelPlacement
    settings : RenderSettings
    camera_offset_px : ndarray, shape (N, 2)
        Offset of the whole picture at each frame (camera shake and drift) [px].
    marker_visible : ndarray, shape (N, W)
        Share of each shown wheel's marker in view at each frame (0: hidden by the fender or a
        card, 1: all of it), averaged over the exposure.
    """

    path: Path
    frame_t_s: np.ndarray
    recording_t_s: np.ndarray
    wheel_rpm: np.ndarray
    angle_turns: np.ndarray
    placements: tuple[WheelPlacement, ...]
    settings: RenderSettings
    camera_offset_px: np.ndarray | None = None
    marker_visible: np.ndarray | None = None


def wheel_turns(t_s: np.ndarray, rpm: np.ndarray, t_query) -> np.ndarray:
    """Exact integral of a piecewise-linear speed from ``t_s[0]`` to each query time [turns].

    Outside the samples the speed is held at the first/last value.
    """
    t = np.asarray(t_s, dtype=float)
    w = np.asarray(rpm, dtype=float) / 60.0
    q = np.atleast_1d(np.asarray(t_query, dtype=float))
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(t))])
    i = np.clip(np.searchsorted(t, q, side="right") - 1, 0, len(t) - 1)
    j = np.minimum(i + 1, len(t) - 1)
    dt_seg = t[j] - t[i]
    slope = np.where(dt_seg > 0, (w[j] - w[i]) / np.where(dt_seg > 0, dt_seg, 1.0), 0.0)
    h = q - t[i]
    inside = (q >= t[0]) & (q <= t[-1])
    part = np.where(inside, w[i] * h + 0.5 * slope * h * h, w[i] * h)
    before = q < t[0]
    return np.where(before, w[0] * (q - t[0]), cum[i] + part)


def wheel_placements(settings: RenderSettings) -> tuple[WheelPlacement, ...]:
    """The wheels side by side, each centred in its share of the frame."""
    n = len(settings.wheels)
    cell_w = settings.width_px / n
    r = 0.38 * min(cell_w, settings.height_px)
    out = []
    for k, wheel in enumerate(settings.wheels):
        cx = cell_w * (k + 0.5)
        cy = settings.height_px / 2.0
        x0 = int(max(0, math.floor(cx - 1.25 * r)))
        y0 = int(max(0, math.floor(cy - 1.25 * r)))
        x1 = int(min(settings.width_px, math.ceil(cx + 1.25 * r)))
        y1 = int(min(settings.height_px, math.ceil(cy + 1.25 * r)))
        out.append(WheelPlacement(wheel, cx, cy, r, (x0, y0, x1 - x0, y1 - y0)))
    return tuple(out)


def _hue_bgr(hue_deg: float, value: float = 235.0) -> tuple[float, float, float]:
    import colorsys

    r, g, b = colorsys.hsv_to_rgb((hue_deg % 360.0) / 360.0, 1.0, value / 255.0)
    return (b * 255.0, g * 255.0, r * 255.0)


class _Scene:
    """Static parts of the picture and the drawing of one frame (pure given its inputs)."""

    def __init__(self, settings: RenderSettings) -> None:
        import cv2

        self.s = settings
        self.places = wheel_placements(settings)
        self._aruco_images: dict[int, np.ndarray] = {}
        h, w = settings.height_px, settings.width_px
        tilt = math.radians(settings.tilt_deg)
        a = math.radians(settings.tilt_axis_deg)
        rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        # The wheel plane seen obliquely: squashed across the tilt axis (an affine view).
        self.view = rot @ np.diag([1.0, math.cos(tilt)]) @ rot.T
        self.minor = math.cos(tilt)
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        bg = 118.0 + 25.0 * (xx / w) - 12.0 * (yy / h)
        self.background = np.repeat(bg[:, :, None], 3, axis=2)
        rng = np.random.default_rng(settings.seed + 7919)
        self.static_blobs: list[tuple[float, float, float, tuple]] = []
        self.moving_blobs: list[tuple[np.ndarray, np.ndarray, float, tuple]] = []
        for k in range(settings.distractors):
            size = float(rng.uniform(0.03, 0.06) * min(w, h))
            colour = _hue_bgr(float(rng.uniform(0, 360)), 220.0)
            p0 = self._free_point(rng, size)
            if k % 2 == 0:
                self.static_blobs.append((p0[0], p0[1], size, colour))
            else:
                p1 = self._free_point(rng, size)
                self.moving_blobs.append((p0, p1, size, colour))
        for x, y, size, colour in self.static_blobs:
            cv2.rectangle(self.background, (int(x - size), int(y - size)),
                          (int(x + size), int(y + size)), colour, -1)
        self.background = np.clip(self.background + 0.5, 0, 255).astype(np.uint8)

    def _free_point(self, rng, size: float) -> np.ndarray:
        """A point whose blob stays clear of every wheel (moving blobs: both ends clear)."""
        w, h = self.s.width_px, self.s.height_px
        for _ in range(500):
            p = rng.uniform([size, size], [w - size, h - size])
            if all(math.hypot(p[0] - pl.cx_px, p[1] - pl.cy_px) > 1.15 * pl.radius_px + 2 * size
                   for pl in self.places):
                return p
        return np.array([size, size])

    def _pt(self, cx: float, cy: float, u: float, v: float) -> tuple[int, int]:
        x, y = self.view @ np.array([u, v])
        return (round((cx + x) * _SCALE), round((cy + y) * _SCALE))

    def draw(self, t_video_s: float, angles_rad: list[np.ndarray],
             offset_px: tuple[float, float] = (0.0, 0.0), flicker_gain: float = 1.0
             ) -> np.ndarray:
        """One BGR frame; ``angles_rad[k]`` are wheel k's angles over the exposure [rad],
        ``offset_px`` the camera's offset, ``flicker_gain`` the light's flicker factor."""
        import cv2

        s = self.s
        frame = self.background.copy()
        for (p0, p1, size, colour) in self.moving_blobs:
            f = 0.5 - 0.5 * math.cos(2 * math.pi * t_video_s / 3.0)
            p = p0 + f * (p1 - p0)
            cv2.circle(frame, (round(p[0] * _SCALE), round(p[1] * _SCALE)), round(size * _SCALE),
                       colour, -1, cv2.LINE_AA, _SHIFT)
        axis_deg = s.tilt_axis_deg
        for k, pl in enumerate(self.places):
            c = (round(pl.cx_px * _SCALE), round(pl.cy_px * _SCALE))
            r = pl.radius_px
            for rr, grey in ((r * 1.08, 38), (r * 0.9, 96), (r * 0.2, 70)):
                cv2.ellipse(frame, c, (round(rr * _SCALE), round(rr * self.minor * _SCALE)),
                            axis_deg, 0, 360, (grey, grey, grey), -1, cv2.LINE_AA, _SHIFT)
            mid = float(angles_rad[k][len(angles_rad[k]) // 2])
            for j in range(5):
                a = mid + j * 2 * math.pi / 5
                p = self._pt(pl.cx_px, pl.cy_px, 0.85 * r * math.cos(a), -0.85 * r * math.sin(a))
                cv2.line(frame, c, p, (150, 150, 150), max(1, round(r * 0.05)), cv2.LINE_AA,
                         _SHIFT)
            if s.marker == "aruco":
                self._aruco(frame, pl, angles_rad[k], k)
            else:
                self._marker(frame, pl, angles_rad[k], _hue_bgr(s.marker_hues_deg[
                    k % len(s.marker_hues_deg)]))
            if s.fender:
                # The fender covers the wheel plane above a chord (image y points down).
                yf = -r * (1.0 - 2.0 * s.fender)
                poly = np.array([self._pt(pl.cx_px, pl.cy_px, u, v) for u, v in
                                 ((-1.15 * r, yf), (1.15 * r, yf), (1.15 * r, -1.12 * r),
                                  (-1.15 * r, -1.12 * r))], np.int32)
                cv2.fillConvexPoly(frame, poly, (62, 64, 68), cv2.LINE_AA, _SHIFT)
        for t0, t1 in s.occlusions_s:
            if t0 <= t_video_s < t1:
                for pl in self.places:
                    x, y, w, h = pl.roi
                    cv2.rectangle(frame, (x, y), (x + w, y + h), (128, 126, 124), -1)
        gain = flicker_gain
        if s.lighting_drift:
            gain *= 1.0 + s.lighting_drift * math.sin(2 * math.pi * t_video_s / 4.0)
        if gain != 1.0:
            frame = cv2.convertScaleAbs(frame, alpha=gain)
        if s.hue_shift_deg:
            # OpenCV's hue is in units of 2 deg; grey pixels have no hue and stay grey.
            shift = round(0.5 * s.hue_shift_deg * math.sin(2 * math.pi * t_video_s / 5.0))
            if shift:
                hsv = cv2.cvtColor(frame, cv2.COLOR_BGR2HSV)
                hue = hsv[..., 0].astype(np.int16) + shift
                hsv[..., 0] = np.mod(hue, 180).astype(np.uint8)
                frame = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)
        if offset_px[0] or offset_px[1]:
            m = np.array([[1.0, 0.0, offset_px[0]], [0.0, 1.0, offset_px[1]]])
            frame = cv2.warpAffine(frame, m, (frame.shape[1], frame.shape[0]),
                                   flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        if s.noise_std:
            # One plane of H x 3W: independent noise in each channel of each pixel.
            noise = np.empty((frame.shape[0], frame.shape[1] * 3), np.int16)
            cv2.randn(noise, 0.0, float(s.noise_std))
            frame = cv2.add(frame, noise.reshape(frame.shape), dtype=cv2.CV_8U)
        if s.jpeg_quality is not None:
            _ok, buf = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, int(s.jpeg_quality)])
            frame = cv2.imdecode(buf, cv2.IMREAD_COLOR)
        return frame

    def _aruco(self, frame: np.ndarray, pl: WheelPlacement, angles: np.ndarray,
               k: int) -> None:
        """ArUco marker ``k`` on the hub, turned by the wheel angle, averaged over the exposure."""
        import cv2

        from .aruco import aruco_dictionary

        if k not in self._aruco_images:
            cells = 8  # 4x4 bits, a black border and a white quiet zone: 8 cells across
            img = np.full((cells * 24, cells * 24), 255, np.uint8)
            img[24:-24, 24:-24] = cv2.aruco.generateImageMarker(aruco_dictionary(), k, 6 * 24)
            self._aruco_images[k] = img
        img = self._aruco_images[k]
        x, y, w, h = pl.roi
        scale = 0.9 * pl.radius_px / img.shape[0]
        centre = np.array([(img.shape[1] - 1) / 2.0, (img.shape[0] - 1) / 2.0])
        acc = np.zeros((h, w), np.float32)
        cover = np.zeros((h, w), np.float32)
        ones = np.full(img.shape, 255, np.uint8)
        for a in angles:
            rot = np.array([[math.cos(a), math.sin(a)], [-math.sin(a), math.cos(a)]])
            lin = self.view @ rot * scale
            shift = np.array([pl.cx_px - x, pl.cy_px - y]) - lin @ centre
            m = np.column_stack([lin, shift])
            acc += cv2.warpAffine(img, m, (w, h), flags=cv2.INTER_AREA)
            cover += cv2.warpAffine(ones, m, (w, h), flags=cv2.INTER_AREA)
        alpha = cover / (255.0 * len(angles))
        box = frame[y:y + h, x:x + w].astype(np.float32)
        box = box * (1.0 - alpha)[:, :, None] + (acc / len(angles))[:, :, None]
        frame[y:y + h, x:x + w] = np.clip(box + 0.5, 0, 255).astype(np.uint8)

    def _marker(self, frame: np.ndarray, pl: WheelPlacement, angles: np.ndarray,
                colour: tuple) -> None:
        """The dot, smeared over the exposure's angles (alpha-blended around its path)."""
        import cv2

        r = pl.radius_px
        size = 0.09 * r
        axes = (round(size * _SCALE), round(size * self.minor * _SCALE))
        centres = [self._pt(pl.cx_px, pl.cy_px, 0.7 * r * math.cos(a), -0.7 * r * math.sin(a))
                   for a in angles]
        if len(centres) == 1:
            cv2.ellipse(frame, centres[0], axes, self.s.tilt_axis_deg, 0, 360, colour, -1,
                        cv2.LINE_AA, _SHIFT)
            return
        xy = np.array(centres, float) / _SCALE
        h, w = frame.shape[:2]
        x0, y0 = (np.floor(xy.min(axis=0) - size - 2)).astype(int).clip(0, [w - 1, h - 1])
        x1, y1 = (np.ceil(xy.max(axis=0) + size + 3)).astype(int).clip(1, [w, h])
        alpha = np.zeros((y1 - y0, x1 - x0), np.float32)
        layer = np.zeros((y1 - y0, x1 - x0), np.uint8)
        off = np.array([x0, y0]) * _SCALE
        for cx, cy in centres:
            layer[:] = 0
            cv2.ellipse(layer, (cx - int(off[0]), cy - int(off[1])), axes, self.s.tilt_axis_deg,
                        0, 360, 255, -1, cv2.LINE_AA, _SHIFT)
            alpha += layer
        alpha *= 1.0 / (255.0 * len(centres))
        box = frame[y0:y1, x0:x1].astype(np.float32)
        box *= (1.0 - alpha)[:, :, None]
        box += alpha[:, :, None] * np.array(colour, np.float32)
        frame[y0:y1, x0:x1] = np.clip(box + 0.5, 0, 255).astype(np.uint8)


def schedule_frames(t_s: np.ndarray, camera_start_s: float, duration_s: float | None,
                    fps: float) -> tuple[np.ndarray, np.ndarray]:
    """Video times and recording times of the frames to render [s].

    Parameters
    ----------
    t_s : ndarray, shape (N,)
        The recording's sample times [s].
    camera_start_s : float
        Recording time of the first frame after the recording's first sample [s].
    duration_s : float or None
        Video length [s]; None: to the recording's end. It may not run past the recording's
        end (the frames are what the recording says, and their number is bounded by it).
    fps : float
        Frame rate [1/s].

    Raises
    ------
    VideoError
        A recording with fewer than two samples, a camera starting after the recording's end,
        a video longer than the recording after the start, fewer than two frames.
    """
    t = np.asarray(t_s, dtype=float)
    if t.size < 2:
        raise VideoError(f"nothing to render: the recording has {t.size} sample"
                         f"{'' if t.size == 1 else 's'} (need at least two)")
    check_times(camera_start_s, duration_s)
    t0 = float(t[0]) + camera_start_s
    last = float(t[-1])
    if not t0 < last:
        raise VideoError(f"nothing to render: the recording ends at {last - t[0]:.3f} s, "
                         f"before the camera starts (--start {camera_start_s:g} s)")
    end = last
    if duration_s is not None:
        # a hair of rounding past the end is the end (--duration 5 of a 5.000 s recording)
        if t0 + duration_s > last + 1e-9 * max(1.0, abs(last)):
            raise VideoError(f"--duration {duration_s:g} s runs past the recording's end: it "
                             f"has {last - t0:.3f} s after --start {camera_start_s:g} s (give at "
                             "most that, or leave --duration out)")
        end = t0 + duration_s
    n = math.floor((end - t0) * fps + 1e-9) + 1
    if n < 2:
        raise VideoError("nothing to render: less than two frames between --start and the end")
    tv = np.arange(n) / fps
    return tv, t0 + tv


def frame_schedule(rec: Recording, settings: RenderSettings) -> tuple[np.ndarray, np.ndarray]:
    """Video times and recording times of the frames to render [s] (:func:`schedule_frames`)."""
    return schedule_frames(rec.t_s, settings.camera_start_s, settings.duration_s, settings.fps)


def _wheel_columns(rec: Recording, wheels: tuple[int, ...]) -> list[np.ndarray]:
    cols = []
    for wheel in wheels:
        col = rec.wheel_rpm[:, wheel - 1]
        if len(rec) < 2 or not np.isfinite(col).all():
            raise VideoError(f"the recording has no complete {WHEEL_COLUMNS[wheel - 1]} column "
                             "to render (make one with `mecanum-hil simulate`)")
        cols.append(col)
    return cols


def wheel_truth(rec: Recording, settings: RenderSettings, t_rec_s: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """True wheel speeds [rpm] and angles [turns] of the shown wheels at recording times."""
    rpm = np.empty((t_rec_s.size, len(settings.wheels)))
    turns = np.empty_like(rpm)
    for k, col in enumerate(_wheel_columns(rec, settings.wheels)):
        rpm[:, k] = np.interp(t_rec_s, rec.t_s, col)
        turns[:, k] = wheel_turns(rec.t_s, col, t_rec_s)
    return rpm, turns


def camera_offsets(settings: RenderSettings, frame_t_s: np.ndarray) -> np.ndarray:
    """Offset of the picture at each frame [px], shape (N, 2): a slow drift plus shake."""
    t = np.asarray(frame_t_s, dtype=float)
    d = settings.drift_px
    drift = np.column_stack([d * np.sin(2 * np.pi * t / 7.0),
                             0.6 * d * np.sin(2 * np.pi * t / 11.0 + 1.0)])
    rng = np.random.default_rng(settings.seed + 104729)
    return drift + rng.normal(0.0, settings.shake_px, (t.size, 2)) if settings.shake_px \
        else drift


def _exposure_offsets(settings: RenderSettings) -> np.ndarray:
    sub = 9 if settings.exposure > 0 else 1
    half = 0.5 * settings.exposure / settings.fps
    return np.linspace(-half, half, sub)


def _exposure_angles(rec: Recording, settings: RenderSettings, t_rec_s: float,
                     cols: list[np.ndarray]) -> list[np.ndarray]:
    """Each shown wheel's marker angle over the exposure of a frame [rad]."""
    sign = -1.0 if settings.mirror else 1.0
    offsets = _exposure_offsets(settings)
    return [0.3 + 1.7 * k + sign * 2 * math.pi * wheel_turns(rec.t_s, col, t_rec_s + offsets)
            for k, col in enumerate(cols)]


def marker_visibility(rec: Recording, settings: RenderSettings) -> np.ndarray:
    """Share of each shown wheel's marker in view at each frame (the fender and the cards
    hide it), averaged over the exposure; shape (N, W)."""
    tv, tr = frame_schedule(rec, settings)
    cols = _wheel_columns(rec, settings.wheels)
    out = np.ones((tv.size, len(cols)))
    if settings.fender and settings.marker == "dot":
        # Height of the dot's centre above the fender's chord, in dot radii (0.7 R and 0.09 R).
        for i in range(tv.size):
            for k, a in enumerate(_exposure_angles(rec, settings, float(tr[i]), cols)):
                d = np.clip(((1.0 - 2.0 * settings.fender) - 0.7 * np.sin(a)) / 0.09, -1.0, 1.0)
                seg = (np.arccos(-d) + d * np.sqrt(1.0 - d * d)) / np.pi
                out[i, k] = float(np.mean(seg))
    for t0, t1 in settings.occlusions_s:
        out[(tv >= t0) & (tv < t1)] = 0.0
    return out


def render_frames(rec: Recording, settings: RenderSettings) -> Iterator[np.ndarray]:
    """The frames of :func:`render_video`, one BGR uint8 array each."""
    tv, tr = frame_schedule(rec, settings)
    scene = _Scene(settings)
    import cv2

    cv2.setRNGSeed(int(settings.seed))
    offsets = _exposure_offsets(settings)
    shifts = camera_offsets(settings, tv)
    cols = _wheel_columns(rec, settings.wheels)
    for i in range(tv.size):
        flicker = 1.0
        if settings.flicker:
            # The exposure integrates the light: short shutters see the flicker most.
            flicker += settings.flicker * float(np.mean(np.cos(
                2 * np.pi * settings.flicker_hz * (tv[i] + offsets))))
        yield scene.draw(float(tv[i]), _exposure_angles(rec, settings, float(tr[i]), cols),
                         (float(shifts[i, 0]), float(shifts[i, 1])), flicker)


def render_video(rec: Recording, path: str | Path, settings: RenderSettings | None = None,
                 progress=None) -> RenderResult:
    """Render the wheels of a recording to a video file (codec by extension, see
    :func:`~mecanum_hil.vision.video.fourcc_for`) and return the truth.

    Parameters
    ----------
    rec : Recording
        Needs the shown wheels' columns filled.
    path : str or Path
        ``.mp4`` (mp4v) or ``.avi`` (MJPG).
    settings : RenderSettings, optional
    progress : callable, optional
        Called as ``progress(done, total)`` after each frame.
    """
    s = settings or RenderSettings()
    fourcc_for(path)
    tv, tr = frame_schedule(rec, s)
    rpm, turns = wheel_truth(rec, s, tr)
    with VideoWriter(path, s.fps, (s.width_px, s.height_px)) as writer:
        for i, frame in enumerate(render_frames(rec, s)):
            writer.write(frame)
            if progress is not None:
                progress(i + 1, tv.size)
    return RenderResult(Path(path), tv, tr, rpm, turns, wheel_placements(s), s,
                        camera_offsets(s, tv), marker_visibility(rec, s))
