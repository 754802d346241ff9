"""A camera's intrinsics and lens distortion (``camera.toml``) and its pose over the floor.

OpenCV's pinhole model with the five-coefficient distortion ``(k1, k2, p1, p2, k3)`` in OpenCV's
order; pixel coordinates have ``(0, 0)`` at the centre of the top-left pixel (OpenCV's
convention, the one its corner detectors use). The camera pose is OpenCV's: ``rvec, tvec`` map
world points into the camera frame (x right, y down, z along the view).

``camera.toml``::

    [camera]
    width_px = 1280
    height_px = 720
    fx_px = 900.0
    fy_px = 900.0
    cx_px = 639.5
    cy_px = 359.5
    distortion = [-0.18, 0.05, 0.0008, -0.0005, 0.0]   # k1, k2, p1, p2, k3
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..io.toml_config import TableReader, load_toml, toml_value, write_toml


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics and lens distortion of one camera.

    Attributes
    ----------
    width_px, height_px : int
        Image size [px].
    fx_px, fy_px : float
        Focal lengths [px].
    cx_px, cy_px : float
        Principal point [px] (0 at the centre of the top-left pixel).
    distortion : tuple of 5 float
        OpenCV's ``(k1, k2, p1, p2, k3)`` [-].
    rms_px : float or None
        RMS reprojection error of the calibration that produced it [px], when known.
    """

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    rms_px: float | None = None

    def __post_init__(self) -> None:
        if self.width_px < 16 or self.height_px < 16:
            raise ConfigError(f"camera size {self.width_px}x{self.height_px} px is too small")
        if not (self.fx_px > 0 and self.fy_px > 0):
            raise ConfigError("camera focal lengths must be > 0")
        if len(self.distortion) != 5:
            raise ConfigError("camera distortion must be five numbers k1, k2, p1, p2, k3")

    @property
    def matrix(self) -> np.ndarray:
        """The 3x3 camera matrix ``K``."""
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px],
                         [0.0, 0.0, 1.0]])

    @property
    def dist(self) -> np.ndarray:
        """Distortion coefficients as OpenCV takes them, shape (5,)."""
        return np.asarray(self.distortion, dtype=float)

    def project(self, points_world: np.ndarray, pose: CameraPose) -> np.ndarray:
        """Image points [px] of world points [m], shape (N, 3) -> (N, 2), distortion applied."""
        import cv2

        pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 1, 3)
        img, _ = cv2.projectPoints(pts, pose.rvec, pose.tvec, self.matrix, self.dist)
        return img.reshape(-1, 2)

    def normalised(self, points_px: np.ndarray, iterations: int = 40) -> np.ndarray:
        """Undistorted normalised image coordinates ``(x/z, y/z)`` of pixel points, (N, 2).

        OpenCV's iterative inversion of the distortion, run to convergence (its default of 5
        iterations leaves errors of ~0.1 px near the corners of a wide lens).
        """
        import cv2

        pts = np.asarray(points_px, dtype=np.float64).reshape(-1, 1, 2)
        if pts.shape[0] == 0:
            return np.empty((0, 2))
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, iterations, 1e-12)
        if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x; 5.x folded it into the one below
            out = cv2.undistortPointsIter(pts, self.matrix, self.dist, None, None, crit)
        else:
            out = cv2.undistortPoints(pts, self.matrix, self.dist, R=None, P=None,
                                      criteria=crit)
        return out.reshape(-1, 2)


@dataclass(frozen=True)
class CameraPose:
    """Where a camera is: OpenCV's world-to-camera rotation vector and translation.

    Attributes
    ----------
    rvec : ndarray, shape (3,)
        Rodrigues rotation vector, world to camera [rad].
    tvec : ndarray, shape (3,)
        Translation, world to camera [m].
    """

    rvec: np.ndarray = field(default_factory=lambda: np.zeros(3))
    tvec: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def rotation(self) -> np.ndarray:
        """World-to-camera rotation matrix."""
        import cv2

        return cv2.Rodrigues(np.asarray(self.rvec, dtype=np.float64))[0]

    @property
    def position_m(self) -> np.ndarray:
        """The camera centre in the world frame [m]."""
        return -self.rotation.T @ np.asarray(self.tvec, dtype=float)

    def summary(self) -> dict:
        """Position [m], view tilt from straight down [deg], the view's azimuth [deg] (from
        world X, counter-clockwise) and OpenCV's rvec/tvec, for JSON."""
        r = self.rotation
        view = r[2]  # the optical axis in the world frame
        tilt = math.degrees(math.acos(max(-1.0, min(1.0, -view[2]))))
        azimuth = math.degrees(math.atan2(view[1], view[0])) if tilt > 1e-6 else 0.0
        return {"position_m": [round(float(v), 5) for v in self.position_m],
                "tilt_deg": round(tilt, 3), "azimuth_deg": round(azimuth, 3),
                "rvec": [float(v) for v in self.rvec], "tvec_m": [float(v) for v in self.tvec]}

    def plane_points(self, camera: CameraModel, points_px: np.ndarray,
                     height_m: float) -> np.ndarray:
        """World ``(X, Y)`` [m] where the rays through pixel points meet the plane
        ``z = height_m``, shape (N, 2); NaN for rays parallel to or pointing away from it."""
        return rays_to_plane(self, camera.normalised(points_px), height_m)


def rays_to_plane(pose: CameraPose, normalised: np.ndarray, height_m: float) -> np.ndarray:
    """World ``(X, Y)`` [m] where rays with normalised image coordinates meet ``z = height_m``.

    Parameters
    ----------
    pose : CameraPose
    normalised : ndarray, shape (N, 2)
        Undistorted normalised coordinates (:meth:`CameraModel.normalised`).
    height_m : float
        Height of the plane [m].
    """
    r = pose.rotation
    n = np.asarray(normalised, dtype=float).reshape(-1, 2)
    u, v = n[:, 0], n[:, 1]
    # the ray (u, v, 1) in the world frame: r.T @ ray, written out (no BLAS call per frame)
    dx = r[0, 0] * u + r[1, 0] * v + r[2, 0]
    dy = r[0, 1] * u + r[1, 1] * v + r[2, 1]
    dz = r[0, 2] * u + r[1, 2] * v + r[2, 2]
    c = pose.position_m
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (height_m - c[2]) / dz
    s = np.where(s > 0, s, np.nan)
    return np.column_stack([c[0] + s * dx, c[1] + s * dy])


def look_at(position_m, target_m, up_hint=(0.0, 1.0, 0.0)) -> CameraPose:
    """The pose of a camera at ``position_m`` looking at ``target_m`` (world, [m]); the image's
    up direction is as close to ``up_hint`` as the view allows."""
    import cv2

    c = np.asarray(position_m, dtype=float)
    z = np.asarray(target_m, dtype=float) - c
    z /= np.linalg.norm(z)
    down = -np.asarray(up_hint, dtype=float)
    y = down - (down @ z) * z
    if np.linalg.norm(y) < 1e-9:
        raise ConfigError("look_at: the up hint is along the view")
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    r = np.vstack([x, y, z])
    rvec = cv2.Rodrigues(r)[0].ravel()
    return CameraPose(rvec, -r @ c)


def load_camera(path: str | Path) -> CameraModel:
    """Read ``camera.toml`` (see the module docstring).

    Raises
    ------
    ConfigError
        Missing file, missing table or key, bad value.
    """
    p = Path(path)
    doc = load_toml(p)
    cam = TableReader(doc, str(p)).sub("camera")
    assert cam is not None
    cam.reject_unknown({"width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px",
                        "distortion", "rms_px", "source", "views"})
    w = cam.whole_number("width_px", minimum=16)
    h = cam.whole_number("height_px", minimum=16)
    rms = cam.number("rms_px", math.nan) if "rms_px" in cam.table else None
    return CameraModel(w, h, cam.number("fx_px", minimum=0, strict_minimum=True),
                       cam.number("fy_px", minimum=0, strict_minimum=True),
                       cam.number("cx_px"), cam.number("cy_px"),
                       cam.numbers("distortion", 5), rms)  # type: ignore[arg-type]


def camera_to_toml(camera: CameraModel, header: str = "", extra: dict | None = None) -> str:
    """``camera.toml`` text for a camera model (floats written to round-trip exactly)."""
    lines = [f"# {line}" for line in header.splitlines()] if header else []
    lines.append("[camera]")
    for key in ("width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px"):
        lines.append(f"{key} = {toml_value(getattr(camera, key))}")
    lines.append(f"distortion = {toml_value([float(v) for v in camera.distortion])}"
                 "   # k1, k2, p1, p2, k3 (OpenCV)")
    if camera.rms_px is not None:
        lines.append(f"rms_px = {toml_value(float(camera.rms_px))}")
    for key, value in (extra or {}).items():
        lines.append(f"{key} = {toml_value(value)}")
    return "\n".join(lines) + "\n"


def save_camera(camera: CameraModel, path: str | Path, header: str = "",
                extra: dict | None = None) -> Path:
    """Write ``camera.toml``."""
    return write_toml(path, camera_to_toml(camera, header, extra), "the camera file")
