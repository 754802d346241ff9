"""The wheel's hub tracked per frame, so a camera that shakes or drifts does not move the angle.

A marker's angle is taken about the centre of its path; when the camera shakes by a pixel, a
marker 100 px from the hub appears to turn by 0.01 rad, which the speed differentiator turns into
rpm of noise. The wheel's dark parts (tyre or rollers, hub, fender) form a rigid shape that turns
about the hub and moves with the camera; the centroid of the dark pixels in the search region
follows the camera, but not the wheel's rotation (a tyre is a ring).

Per frame: the pixels whose three channels all lie below a threshold (so saturated markers and
coloured objects never count as dark), scaled by the region's mean brightness against the first
frame (a change of exposure or flickering light keeps the same pixels dark); the centroid of
that mask on every second pixel (its long curved edges make it sub-pixel). A frame whose dark area
differs from the video's median by more than :data:`AREA_TOLERANCE` (something dark entered the
region, or a card hid the wheel) gets the offset interpolated from its neighbours.
"""

from __future__ import annotations

import numpy as np

from .detect import clip_roi

#: Margin added around the search region on each side, as a share of its size.
WINDOW_MARGIN = 0.1
#: Sampling step of the search region [px].
STRIDE = 2
#: Relative change of the dark area beyond which a frame's centroid is not trusted.
AREA_TOLERANCE = 0.1
#: Spread of the measured offsets below which the camera counts as still [px]: the offsets are
#: then not applied (they would only add the tracker's own jitter).
STILL_CAMERA_PX = 0.1


class HubTracker:
    """Centroid of the wheel's dark parts in one search region of each frame.

    Parameters
    ----------
    roi : (x, y, w, h) or None
        Search region [px] (the whole frame for ``None``), widened by :data:`WINDOW_MARGIN`
        within the frame; the wheel's dark parts should stay inside it, with some lighter
        background around them, however the camera moves.
    frame_size : (width, height)
        [px].
    """

    def __init__(self, roi: tuple[int, int, int, int] | None,
                 frame_size: tuple[int, int]) -> None:
        x0, y0, x1, y1 = clip_roi(roi, frame_size)
        # A margin around the search region, so the wheel's dark parts stay inside as the
        # camera drifts (a part leaving the window would pull the centroid).
        mx, my = round(WINDOW_MARGIN * (x1 - x0)), round(WINDOW_MARGIN * (y1 - y0))
        self.x0, self.y0 = max(0, x0 - mx), max(0, y0 - my)
        self.x1, self.y1 = min(frame_size[0], x1 + mx), min(frame_size[1], y1 + my)
        self.threshold = -1.0
        self.ref_level = 0.0
        self._ramp_x = self._ramp_y = np.empty(0)

    def __call__(self, frame: np.ndarray) -> tuple[float, float, float]:
        """``(x [px], y [px], dark area [px^2])`` of one BGR frame (NaN when nothing is dark)."""
        import cv2

        # Every second row and column: a quarter of the cost; the mask's long curved edges
        # still put the centroid within a few tenths of a pixel.
        win = frame[self.y0:self.y1, self.x0:self.x1]
        if STRIDE > 1:
            win = cv2.resize(win, None, fx=1.0 / STRIDE, fy=1.0 / STRIDE,
                             interpolation=cv2.INTER_AREA)
        b, g, r, _ = cv2.mean(win)
        level = (b + g + r) / 3.0
        if self.threshold < 0:
            grey = cv2.cvtColor(np.ascontiguousarray(win), cv2.COLOR_BGR2GRAY)
            otsu, _ = cv2.threshold(grey, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
            self.threshold, self.ref_level = float(otsu), max(level, 1.0)
        t = min(254, round(self.threshold * level / self.ref_level))
        mask = cv2.inRange(win, (0, 0, 0), (t, t, t))
        # The centroid from the column and row sums: a tenth of cv2.moments' cost here.
        cols = cv2.reduce(mask, 0, cv2.REDUCE_SUM, dtype=cv2.CV_32S).ravel()
        rows = cv2.reduce(mask, 1, cv2.REDUCE_SUM, dtype=cv2.CV_32S).ravel()
        total = float(cols.sum())
        if total <= 0:
            return float("nan"), float("nan"), 0.0
        # Pixel (i, j) of the reduced window covers [STRIDE*i, STRIDE*(i+1)) of the frame.
        if self._ramp_x.size != cols.size or self._ramp_y.size != rows.size:
            self._ramp_x = np.arange(cols.size, dtype=np.float64)
            self._ramp_y = np.arange(rows.size, dtype=np.float64)
        cx = float(cols @ self._ramp_x) / total
        cy = float(rows @ self._ramp_y) / total
        return (self.x0 + STRIDE * cx, self.y0 + STRIDE * cy, total / 255.0)


def camera_offsets(hub: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Offset of the hub from its position in the first frame, per frame [px].

    Parameters
    ----------
    hub : ndarray, shape (N, 3)
        :class:`HubTracker` results.

    Returns
    -------
    offsets : ndarray, shape (N, 2)
        Zero when the camera is still (spread below :data:`STILL_CAMERA_PX`).
    trusted : ndarray of bool, shape (N,)
        Frames whose own centroid was used (the others are interpolated).
    """
    hub = np.asarray(hub, dtype=float).reshape(-1, 3)
    n = hub.shape[0]
    area = hub[:, 2]
    ok = np.isfinite(hub[:, 0]) & (area > 0)
    if ok.sum() < 2:
        return np.zeros((n, 2)), ok
    med = float(np.median(area[ok]))
    ok &= np.abs(area - med) <= AREA_TOLERANCE * med
    if ok.sum() < 2:
        return np.zeros((n, 2)), ok
    idx = np.arange(n)
    xy = np.column_stack([np.interp(idx, idx[ok], hub[ok, k]) for k in (0, 1)])
    off = xy - xy[0]
    if float(np.max(np.std(off, axis=0))) < STILL_CAMERA_PX:
        return np.zeros((n, 2)), ok
    return off, ok
