"""Camera calibration with a ChArUco board (OpenCV's ``CharucoDetector`` and
``calibrateCamera``), refusing views that leave part of the image uncovered.

The board is given as ``charuco:COLSxROWS:SQUARE_M:MARKER_M[:DICTIONARY]`` (squares across and
down, the square's and the marker's side [m], OpenCV's dictionary, default ``DICT_5X5_100``).
Lens distortion is only well determined where board corners were seen: a calibration whose
corners leave a ninth of the image (3 x 3 cells) empty is refused, naming the cells.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import VideoError
from .camera import CameraModel, CameraPose, rays_to_plane
from .scene import dictionary_by_name
from .video import iter_frames, open_video

#: Image file types read from a folder of calibration views.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
#: Fewest board corners for a view to count.
MIN_CORNERS = 8
#: Fewest views for a calibration.
MIN_VIEWS = 5
#: Fewest corners (over all views) in each of the 3 x 3 cells of the image.
MIN_CELL_CORNERS = 4
#: Most squares across or down a board: far beyond any printed board (OpenCV's board and
#: detector grow with the squares: 1000x1000 ran for minutes, 100000x100000 took 22 GB).
MAX_BOARD_SQUARES = 100
#: Most views used from a video (each is held in memory and calibrated on; 20..60 suffice).
MAX_VIEWS = 500
_CELL_NAMES = (("top-left", "top", "top-right"), ("left", "centre", "right"),
               ("bottom-left", "bottom", "bottom-right"))


@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board: squares across and down, square and marker side [m], dictionary."""

    cols: int
    rows: int
    square_m: float
    marker_m: float
    dictionary: str = "DICT_5X5_100"

    @property
    def markers(self) -> int:
        """Markers on the board (one on every other square): ``cols * rows // 2``."""
        return self.cols * self.rows // 2

    def board(self):
        """OpenCV's ``CharucoBoard``."""
        import cv2

        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_m, self.marker_m,
                                      dictionary_by_name(self.dictionary))


def parse_board(text: str) -> BoardSpec:
    """``charuco:COLSxROWS:SQUARE_M:MARKER_M[:DICTIONARY]`` -> :class:`BoardSpec`.

    Raises
    ------
    VideoError
        Malformed text, fewer than 3 or more than :data:`MAX_BOARD_SQUARES` squares a side,
        sizes out of order, or more markers (``COLS * ROWS // 2``) than the dictionary has.
    ConfigError
        An unknown dictionary.
    """
    parts = text.split(":")
    bad = VideoError(f"--board {text!r}: expected charuco:COLSxROWS:SQUARE_M:MARKER_M"
                     "[:DICTIONARY], e.g. charuco:7x5:0.04:0.03")
    if len(parts) not in (4, 5) or parts[0].lower() != "charuco":
        raise bad
    try:
        cols, rows = (int(v) for v in parts[1].lower().split("x"))
        square, marker = float(parts[2]), float(parts[3])
    except ValueError:
        raise bad from None
    if cols < 3 or rows < 3 or not (0 < marker < square) or not math.isfinite(square):
        raise VideoError(f"--board {text!r}: needs at least 3x3 squares and 0 < MARKER_M < "
                         "SQUARE_M")
    if max(cols, rows) > MAX_BOARD_SQUARES:
        raise VideoError(f"--board {text!r}: at most {MAX_BOARD_SQUARES} squares across and "
                         f"down, got {cols}x{rows}")
    spec = BoardSpec(cols, rows, square, marker, *(parts[4:] or []))
    available = len(dictionary_by_name(spec.dictionary).bytesList)
    if spec.markers > available:
        raise VideoError(f"--board {text!r}: a {cols}x{rows} board has {spec.markers} markers, "
                         f"more than the {available} of the dictionary {spec.dictionary} (give "
                         "fewer squares or a larger dictionary, e.g. charuco:...:DICT_5X5_1000)")
    return spec


@dataclass(frozen=True)
class Calibration:
    """The result of :func:`calibrate`.

    Attributes
    ----------
    camera : CameraModel
        With ``rms_px`` set.
    views_used : int
    corners : int
        Board corners over all views.
    coverage : tuple of str
        The 3 x 3 cells of the image with corners.
    """

    camera: CameraModel
    views_used: int
    corners: int
    coverage: tuple[str, ...]


def read_views(source: str | Path, max_views: int = 60) -> list[np.ndarray]:
    """Grey images from a folder of images, one image, or a video (up to ``max_views`` frames
    spread over it, at most :data:`MAX_VIEWS`)."""
    import cv2

    if not 1 <= max_views <= MAX_VIEWS:
        raise VideoError(f"--max-views must be within 1..{MAX_VIEWS}, got {max_views}")
    p = Path(source)
    if p.is_dir():
        files = sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise VideoError(f"{p}: no images ({', '.join(IMAGE_SUFFIXES)}) in the folder")
        out = []
        for f in files:
            img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise VideoError(f"{f}: not an image OpenCV can read")
            out.append(img)
        return out
    if p.suffix.lower() in IMAGE_SUFFIXES:
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise VideoError(f"{p}: file not found or not an image OpenCV can read")
        return [img]
    cap, _ = open_video(p)
    # every stride-th frame, the stride doubling whenever 2 x max_views are held: frames spread
    # over the whole video in bounded memory (a minute of 1080p would be ~4 GB of grey frames;
    # the container's frame count, which would allow picking ahead, may be wrong)
    frames: list[np.ndarray] = []
    stride = 1
    try:
        for index, _, f in iter_frames(cap):
            if index % stride:
                continue
            frames.append(cv2.cvtColor(f, cv2.COLOR_BGR2GRAY))
            if len(frames) >= 2 * max_views:
                frames = frames[::2]
                stride *= 2
    finally:
        cap.release()
    if len(frames) > max_views:
        pick = np.linspace(0, len(frames) - 1, max_views).round().astype(int)
        frames = [frames[i] for i in pick]
    return frames


def _cells(points: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Corner counts per 3 x 3 cell of the image."""
    w, h = size
    cx = np.clip((points[:, 0] * 3 / w).astype(int), 0, 2)
    cy = np.clip((points[:, 1] * 3 / h).astype(int), 0, 2)
    counts = np.zeros((3, 3), int)
    np.add.at(counts, (cy, cx), 1)
    return counts


def calibrate(views: list[np.ndarray], spec: BoardSpec, source: str = "views") -> Calibration:
    """Intrinsics and distortion from grey views of a ChArUco board.

    Raises
    ------
    VideoError
        Images of different sizes, fewer than :data:`MIN_VIEWS` views with the board, corners
        missing from part of the image (named), or OpenCV's calibration failing.
    """
    import cv2

    if not views:
        raise VideoError(f"{source}: no views")
    h, w = views[0].shape[:2]
    if any(v.shape[:2] != (h, w) for v in views):
        raise VideoError(f"{source}: the views differ in size")
    board = spec.board()
    detector = cv2.aruco.CharucoDetector(board)
    obj_list, img_list = [], []
    for gray in views:
        corners, ids, _, _ = detector.detectBoard(gray)
        if ids is None or len(ids) < MIN_CORNERS:
            continue
        obj, img = board.matchImagePoints(corners, ids)
        if obj is None or len(obj) < MIN_CORNERS:
            continue
        obj_list.append(obj.reshape(-1, 1, 3).astype(np.float32))
        img_list.append(img.reshape(-1, 1, 2).astype(np.float32))
    if len(obj_list) < MIN_VIEWS:
        raise VideoError(f"{source}: the board ({spec.cols}x{spec.rows} {spec.dictionary}) was "
                         f"found in {len(obj_list)} of {len(views)} views; need at least "
                         f"{MIN_VIEWS} (check --board)")
    pts = np.concatenate([i.reshape(-1, 2) for i in img_list])
    counts = _cells(pts, (w, h))
    missing = [_CELL_NAMES[r][c] for r in range(3) for c in range(3)
               if counts[r, c] < MIN_CELL_CORNERS]
    if missing:
        raise VideoError(f"{source}: the board's corners do not cover the image: nothing in "
                         f"the {', '.join(missing)} part{'s' if len(missing) > 1 else ''} of the "
                         "picture (film the board there too; lens distortion is only known "
                         "where corners were seen)")
    try:
        rms, k, dist, _, _ = cv2.calibrateCamera(obj_list, img_list, (w, h), None, None)
    except cv2.error as err:
        raise VideoError(f"{source}: OpenCV's calibration failed: {err}") from err
    d = np.zeros(5)
    d[:min(5, dist.size)] = dist.ravel()[:5]
    camera = CameraModel(w, h, float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]),
                         tuple(float(v) for v in d), float(rms))  # type: ignore[arg-type]
    covered = tuple(_CELL_NAMES[r][c] for r in range(3) for c in range(3) if counts[r, c])
    return Calibration(camera, len(obj_list), len(pts), covered)


@functools.lru_cache(maxsize=4)
def _pixel_rays(camera: CameraModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normalised rays of the pixel centres and their derivatives along x and y (the map is
    smooth: sub-pixel rays from the derivatives)."""
    w, h = camera.width_px, camera.height_px
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    n = camera.normalised(np.column_stack([xx.ravel(), yy.ravel()])).reshape(h, w, 2)
    return n, np.gradient(n, axis=1), np.gradient(n, axis=0)


def render_board_view(spec: BoardSpec, camera: CameraModel, pose: CameraPose,
                      noise_std: float = 0.0, seed: int = 0, supersample: int = 2
                      ) -> np.ndarray:
    """A grey picture of the board seen by ``camera`` from ``pose`` (board-to-camera; the
    board's frame as OpenCV's ``CharucoBoard`` defines it: origin at a corner, z = 0), by ray
    casting through the lens (for tests: a view with a known truth)."""
    import cv2

    ppm = 4000.0  # texture pixels per metre of board
    tex_w = round(spec.cols * spec.square_m * ppm)
    tex_h = round(spec.rows * spec.square_m * ppm)
    tex = spec.board().generateImage((tex_w, tex_h), marginSize=0, borderBits=1)
    # a white margin around the board, as printed on paper
    pad = int(0.6 * spec.square_m * ppm)
    tex = cv2.copyMakeBorder(tex, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)
    tex = tex.astype(np.float32)
    w, h = camera.width_px, camera.height_px
    acc = np.zeros((h, w), np.float32)
    n0, dn_du, dn_dv = _pixel_rays(camera)
    for i in range(supersample):
        for j in range(supersample):
            du, dv = (i + 0.5) / supersample - 0.5, (j + 0.5) / supersample - 0.5
            n = (n0 + du * dn_du + dv * dn_dv).reshape(-1, 2)
            xy = rays_to_plane(pose, n, 0.0).reshape(h, w, 2)
            mx = (xy[..., 0] * ppm + pad - 0.5).astype(np.float32)
            my = (xy[..., 1] * ppm + pad - 0.5).astype(np.float32)
            acc += cv2.remap(tex, np.nan_to_num(mx, nan=-1e4), np.nan_to_num(my, nan=-1e4),
                             cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=90.0)
    img = acc / supersample ** 2
    img = 40.0 + img * (200.0 / 255.0)
    if noise_std > 0:
        img += np.random.default_rng(seed).standard_normal(img.shape).astype(np.float32) * \
            noise_std
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)
