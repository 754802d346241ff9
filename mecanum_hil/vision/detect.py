"""Marker candidates in one frame: saturated blobs with a sub-pixel centroid.

Per frame the search region is looked at on a coarse grid (every ``stride``-th pixel) for
saturated pixels (``max(B,G,R) - min(B,G,R)``, hue-blind) or pixels inside a pinned HSV box; each
connected blob is then measured at full resolution in a small window: its centroid is weighted by
how far each pixel's saturation exceeds the background's, which makes it sub-pixel (anti-aliased
and blurred edges count by their share). Which blob is the marker is decided later, over the
whole video (:func:`~mecanum_hil.vision.geometry.select_track`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import VideoError

#: Saturation (max - min channel, 0..255) from which a pixel may belong to a marker.
MIN_SATURATION = 70
#: Saturation counted as background in the centroid weights.
BACKGROUND_SATURATION = 30
#: Largest number of blobs kept per frame and region (the biggest ones).
MAX_BLOBS = 8
#: While a single blob moves by at least FOLLOW_MIN_STEP_PX a frame (the marker turning), the
#: next frame is searched only around where it should be (its last step again), FOLLOW_MARGIN_PX
#: beyond its size and half its step; the whole region is searched again every
#: FOLLOW_FULL_EVERY frames, and whenever that window shows anything but the one blob whole.
FOLLOW_MIN_STEP_PX = 0.5
FOLLOW_MARGIN_PX = 16
FOLLOW_FULL_EVERY = 8


@dataclass(frozen=True)
class MarkerSpec:
    """What the marker looks like.

    Attributes
    ----------
    kind : str
        ``"auto"`` (any saturated dot), ``"hsv"`` (a pinned colour) or ``"aruco"`` (see
        :mod:`~mecanum_hil.vision.aruco`).
    hsv_low, hsv_high : tuple of 3 int or None
        OpenCV HSV box (H 0..179, S, V 0..255) for ``"hsv"``; ``hsv_low[0] > hsv_high[0]``
        wraps around red.
    min_saturation : int
        Saturation threshold of ``"auto"`` (0..255).
    """

    kind: str = "auto"
    hsv_low: tuple[int, int, int] | None = None
    hsv_high: tuple[int, int, int] | None = None
    min_saturation: int = MIN_SATURATION

    def __post_init__(self) -> None:
        if self.kind not in ("auto", "hsv", "aruco"):
            raise VideoError(f"unknown marker kind '{self.kind}' (auto, hsv, aruco)")
        if self.kind == "hsv" and (self.hsv_low is None or self.hsv_high is None):
            raise VideoError("an HSV marker needs a low and a high HSV bound")


def parse_hsv(text: str) -> MarkerSpec:
    """``"H1,S1,V1:H2,S2,V2"`` (OpenCV HSV, H 0..179) as a pinned-colour marker."""
    try:
        lo_s, hi_s = text.split(":")
        lo = tuple(int(v) for v in lo_s.split(","))
        hi = tuple(int(v) for v in hi_s.split(","))
    except ValueError:
        raise VideoError(f"--marker-hsv '{text}': expected H1,S1,V1:H2,S2,V2 "
                         "(e.g. 50,100,80:70,255,255)") from None
    if len(lo) != 3 or len(hi) != 3:
        raise VideoError(f"--marker-hsv '{text}': expected three numbers on each side")
    for v, top in zip(lo + hi, (179, 255, 255) * 2, strict=True):
        if not 0 <= v <= top:
            raise VideoError(f"--marker-hsv '{text}': H is 0..179, S and V are 0..255")
    return MarkerSpec("hsv", lo, hi)  # type: ignore[arg-type]


def parse_roi(text: str, default_wheel: int = 1) -> tuple[int, tuple[int, int, int, int]]:
    """``"N:x,y,w,h"`` or ``"x,y,w,h"`` as ``(wheel, (x, y, w, h))``."""
    wheel = default_wheel
    body = text
    if ":" in text:
        head, body = text.split(":", 1)
        try:
            wheel = int(head)
        except ValueError:
            raise VideoError(f"--roi '{text}': the wheel before ':' must be 1..4") from None
    try:
        x, y, w, h = (int(v) for v in body.split(","))
    except ValueError:
        raise VideoError(f"--roi '{text}': expected [N:]x,y,w,h in pixels") from None
    if wheel not in (1, 2, 3, 4):
        raise VideoError(f"--roi '{text}': wheel must be 1..4")
    if w < 8 or h < 8 or x < 0 or y < 0:
        raise VideoError(f"--roi '{text}': needs x, y >= 0 and a size of at least 8x8 px")
    return wheel, (x, y, w, h)


def _hue_deg(b: float, g: float, r: float) -> float:
    mx, mn = max(b, g, r), min(b, g, r)
    if mx - mn <= 1e-9:
        return 0.0
    if mx == r:
        h = (g - b) / (mx - mn)
    elif mx == g:
        h = 2.0 + (b - r) / (mx - mn)
    else:
        h = 4.0 + (r - g) / (mx - mn)
    return (60.0 * h) % 360.0



def clip_roi(roi: tuple[int, int, int, int] | None,
             frame_size: tuple[int, int]) -> tuple[int, int, int, int]:
    """A region ``(x, y, w, h)`` [px] clipped to the frame, as ``(x0, y0, x1, y1)``.

    ``None`` is the whole frame. Raises :class:`VideoError` when less than 8 x 8 px remain.
    """
    fw, fh = frame_size
    x, y, w, h = roi if roi is not None else (0, 0, fw, fh)
    x0, y0, x1, y1 = max(0, x), max(0, y), min(fw, x + w), min(fh, y + h)
    if x1 - x0 < 8 or y1 - y0 < 8:
        raise VideoError(f"--roi {x},{y},{w},{h} lies outside the {fw}x{fh} frame")
    return x0, y0, x1, y1

#: A row of three: the structuring element that spans one pixel's interleaved B, G and R.
_THREE_ACROSS = np.ones((1, 3), dtype=np.uint8)


class BlobDetector:
    """Find marker candidates in one region of each frame.

    Parameters
    ----------
    spec : MarkerSpec
    roi : (x, y, w, h)
        Search region [px], clipped to the frame.
    frame_size : (width, height)
        [px].
    """

    def __init__(self, spec: MarkerSpec, roi: tuple[int, int, int, int] | None,
                 frame_size: tuple[int, int]) -> None:
        self.x0, self.y0, self.x1, self.y1 = clip_roi(roi, frame_size)
        self.spec = spec
        #: Once the marker's path is known (:meth:`focus`), blobs far from it are not measured.
        self.path = None
        self.path_margin = 0.0
        self.box = (self.x0, self.y0, self.x1, self.y1)  # where each frame is searched
        # A coarse grid of about 200 px across finds dots of a few px radius and keeps the cost
        # per frame far below decoding's.
        self.stride = max(1, math.ceil(max(self.x1 - self.x0, self.y1 - self.y0) / 200))
        # Following one moving blob (see :meth:`_near`): its position relative to the hub and
        # its last step [px], the last single blob's position, the frames since the whole
        # region was searched, and the blobs' extent [px].
        self._follow: tuple[tuple[float, float], tuple[float, float]] | None = None
        self._single: tuple[float, float] | None = None
        self._since_full = 0
        self._extent = 0
        self._bg = np.empty((0, 0), dtype=np.uint8)  # see _background

    def _background(self, shape: tuple[int, int]) -> np.ndarray:
        """An array of :data:`BACKGROUND_SATURATION` of this shape (a view of a kept one)."""
        bg = self._bg
        if bg.shape[0] < shape[0] or bg.shape[1] < shape[1]:
            bg = self._bg = np.full((max(shape[0], bg.shape[0]), max(shape[1], bg.shape[1])),
                                    BACKGROUND_SATURATION, dtype=np.uint8)
        return bg[:shape[0], :shape[1]]

    def focus(self, path, margin: float = 0.35) -> None:
        """Measure only blobs whose coarse centre lies within ``margin`` (relative radius) of
        ``path`` (an :class:`~mecanum_hil.vision.geometry.Ellipse`): distractors cost little."""
        self.path = path
        self.path_margin = margin
        self._path_cos_sin = (math.cos(math.radians(path.angle_deg)),
                              math.sin(math.radians(path.angle_deg)))
        self._follow = self._single = None
        # Search only the path's bounding box (with the margin) from now on.
        reach = (1.0 + margin) * max(path.a_px, path.b_px) + 2 * self.stride
        self.box = (max(self.x0, int(path.cx_px - reach)), max(self.y0, int(path.cy_px - reach)),
                    min(self.x1, math.ceil(path.cx_px + reach)),
                    min(self.y1, math.ceil(path.cy_px + reach)))

    @property
    def size_px(self) -> float:
        """Larger side of the search region [px]."""
        return float(max(self.x1 - self.x0, self.y1 - self.y0))

    def _mask(self, small: np.ndarray) -> np.ndarray:
        """Pixels inside the pinned HSV box (255) of a contiguous BGR image."""
        import cv2

        hsv = cv2.cvtColor(small, cv2.COLOR_BGR2HSV)
        lo, hi = self.spec.hsv_low, self.spec.hsv_high
        if lo[0] <= hi[0]:
            return cv2.inRange(hsv, np.array(lo), np.array(hi))
        return cv2.bitwise_or(
            cv2.inRange(hsv, np.array(lo), np.array((179, hi[1], hi[2]))),
            cv2.inRange(hsv, np.array((0, lo[1], lo[2])), np.array(hi)))

    def __call__(self, frame: np.ndarray, shift_px: tuple[float, float] = (0.0, 0.0)
                 ) -> np.ndarray:
        """Candidates in a BGR frame: rows ``(x [px], y [px], hue [deg], weight, area [px^2])``.

        ``shift_px`` is the camera's offset at this frame (the hub's motion): the focused path
        and its box move with it. The candidates are in the frame's own coordinates. A single
        blob that moves is looked for only near where its last step takes it (see
        :data:`FOLLOW_FULL_EVERY`); when it is found there alone, it is measured as the whole
        search would measure it (which would also see any other blob that appeared elsewhere
        since the last whole search).
        """
        x0, y0, x1, y1 = self.box
        sx, sy = shift_px
        if self.path is not None and (sx or sy):
            dx, dy = round(sx), round(sy)
            x0, x1 = max(self.x0, x0 + dx), min(self.x1, x1 + dx)
            y0, y1 = max(self.y0, y0 + dy), min(self.y1, y1 + dy)
            if x1 - x0 < 4 or y1 - y0 < 4:
                self._follow = self._single = None
                return np.empty((0, 5))
        if self._follow is not None and self._since_full < FOLLOW_FULL_EVERY:
            out = self._near(frame, (x0, y0, x1, y1), sx, sy)
            if out is not None:
                self._since_full += 1
                self._followed(out, sx, sy)
                return out
        out, boxes = self._search(frame, x0, y0, x1, y1, sx, sy)
        self._since_full = 1
        self._extent = max((max(bw, bh) * self.stride for _, _, bw, bh in boxes), default=0)
        self._followed(out, sx, sy)
        return out

    def _followed(self, out: np.ndarray, sx: float, sy: float) -> None:
        """Follow a single blob that moves (the marker turning) from frame to frame."""
        if out.shape[0] != 1:
            self._follow = self._single = None
            return
        pos = (out[0, 0] - sx, out[0, 1] - sy)  # relative to the hub
        last, self._single = self._single, pos
        if last is None:
            self._follow = None
            return
        step = (pos[0] - last[0], pos[1] - last[1])
        # A blob at rest may be a distractor while the marker is hidden: not followed.
        self._follow = (pos, step) if math.hypot(*step) >= FOLLOW_MIN_STEP_PX else None

    def _near(self, frame: np.ndarray, box: tuple[int, int, int, int], sx: float, sy: float
              ) -> np.ndarray | None:
        """The followed blob searched only around where it should be now; None unless exactly
        that one blob is found there, wholly inside the window (then it is measured exactly as
        the whole search would: same grid, same window)."""
        x0, y0, x1, y1 = box
        s = self.stride
        (px, py), (vx, vy) = self._follow
        cx, cy = px + vx + sx, py + vy + sy
        half = FOLLOW_MARGIN_PX + self._extent + 0.5 * math.hypot(vx, vy)
        # The window on the search's own grid (its origin a whole number of steps from the
        # box's), within the box.
        wx0 = max(x0, x0 + s * math.floor((cx - half - x0) / s))
        wy0 = max(y0, y0 + s * math.floor((cy - half - y0) / s))
        wx1 = min(x1, math.ceil(cx + half))
        wy1 = min(y1, math.ceil(cy + half))
        if wx1 - wx0 < 4 * s or wy1 - wy0 < 4 * s:
            return None
        out, boxes = self._search(frame, wx0, wy0, wx1, wy1, sx, sy)
        if out.shape[0] != 1 or len(boxes) != 1:
            return None
        bx, by, bw, bh = boxes[0]
        cw, ch = -(-(wx1 - wx0) // s), -(-(wy1 - wy0) // s)
        # Clear of the window's sides that are not the box's own (there the whole search would
        # have seen more of the blob, or measured it in a wider window).
        if ((bx < 2 and wx0 > x0) or (by < 2 and wy0 > y0)
                or (bx + bw > cw - 3 and wx1 < x1) or (by + bh > ch - 3 and wy1 < y1)):
            return None
        return out

    def _search(self, frame: np.ndarray, x0: int, y0: int, x1: int, y1: int, sx: float,
                sy: float) -> tuple[np.ndarray, list]:
        """Candidates in ``frame[y0:y1, x0:x1]`` and the coarse boxes of the blobs measured."""
        import cv2

        crop = frame[y0:y1, x0:x1]
        s = self.stride
        hc, wc = crop.shape[:2]
        if self.spec.kind == "hsv":
            mask = self._mask(np.ascontiguousarray(crop[::s, ::s]))
        else:
            # Each channel of the grid copied out once (numpy's operations on the strided
            # three-channel view would copy each operand again, five times over): 40 % less.
            small = crop[::s, ::s]
            b = np.ascontiguousarray(small[..., 0])
            g = np.ascontiguousarray(small[..., 1])
            r = np.ascontiguousarray(small[..., 2])
            sat = np.maximum(np.maximum(b, g), r) - np.minimum(np.minimum(b, g), r)
            mask = (sat >= self.spec.min_saturation).view(np.uint8)
        if not cv2.countNonZero(mask):  # nothing saturated (the marker hidden): no contours
            return np.empty((0, 5)), []
        # Outer contours are an order of magnitude cheaper than labelling connected components.
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        if not contours:
            return np.empty((0, 5)), []
        boxes = sorted((cv2.boundingRect(c) for c in contours), key=lambda b: -b[2] * b[3])
        if self.path is not None and boxes:
            # The coarse centres' radius ratio on the path (Ellipse.unit, one point at a time:
            # there are only a few).
            p = self.path
            ct, st = self._path_cos_sin
            kept_boxes = []
            for b in boxes:
                bx, by, bw, bh = b
                dx = x0 + (bx + 0.5 * bw) * s - sx - p.cx_px
                dy = y0 + (by + 0.5 * bh) * s - sy - p.cy_px
                rho = math.hypot((ct * dx + st * dy) / p.a_px, (-st * dx + ct * dy) / p.b_px)
                if abs(rho - 1.0) <= self.path_margin:
                    kept_boxes.append(b)
            boxes = kept_boxes
        out = []
        kept = []
        for bx, by, bw, bh in boxes[:MAX_BLOBS]:
            wx0, wy0 = max(0, (bx - 1) * s), max(0, (by - 1) * s)
            wx1, wy1 = min(wc, (bx + bw + 1) * s), min(hc, (by + bh + 1) * s)
            win = crop[wy0:wy1, wx0:wx1]
            # max(B,G,R) - min(B,G,R): the window as one channel of interleaved B, G, R, whose
            # morphological gradient (dilation minus erosion) over three neighbours is, at each
            # pixel's G, that pixel's saturation (a third fewer OpenCV calls than splitting the
            # channels; the same numbers).
            h, w = win.shape[:2]
            grad = cv2.morphologyEx(np.ascontiguousarray(win).reshape(h, 3 * w),
                                    cv2.MORPH_GRADIENT, _THREE_ACROSS)
            sat = np.ascontiguousarray(grad[:, 1::3])
            # Saturates at 0; against an array of the background's level (a scalar operand
            # costs OpenCV's binding twice the operation).
            weight = cv2.subtract(sat, self._background(sat.shape))
            if self.spec.kind == "hsv":
                weight = cv2.bitwise_and(weight, self._mask(win))
            mom = cv2.moments(weight)
            total = mom["m00"]
            if total <= 0.0:
                continue
            mean = cv2.mean(win, mask=weight)  # the pixels with a weight (non-zero)
            # The area (pixels above the background's saturation) hardly changes with the light;
            # a marker partly hidden shows a smaller one.
            out.append((x0 + wx0 + mom["m10"] / total, y0 + wy0 + mom["m01"] / total,
                        _hue_deg(mean[0], mean[1], mean[2]), total, cv2.countNonZero(weight)))
            kept.append((bx, by, bw, bh))
        return np.array(out, dtype=float).reshape(-1, 5), kept
