"""The wheel's hub tracked per frame, so a camera that shakes or drifts does not move the angle.

A marker's angle is taken about the centre of its path; when the camera shakes by a pixel, a
marker 100 px from the hub appears to turn by 0.01 rad, which the speed differentiator turns into
rpm of noise. The wheel's dark parts (tyre or rollers, hub, fender) form a rigid shape that turns
about the hub and moves with the camera; the centroid of the dark pixels in the search region
follows the camera, but not the wheel's rotation (a tyre is a ring).

Dark: the pixels whose three channels all lie below a threshold (so saturated markers and
coloured objects never count), scaled by the light's level against the first frame (a change of
exposure or flickering light keeps the same pixels dark). The first frame's hub is the centroid
of that mask on every second pixel; every later frame's is that plus the shift of the mask's
edges, read on short profiles across them and solved by least squares (:class:`HubTracker`: a
few thousand pixels a frame, a tenth of the centroid's error), or the centroid again where too
few edges agree. A frame whose dark area differs from the video's median by more than
:data:`AREA_TOLERANCE` (something dark entered the region, or a card hid the wheel) gets the
offset interpolated from its neighbours.
"""

from __future__ import annotations

import math

import numpy as np

from .detect import clip_roi

#: Margin added around the search region on each side, as a share of its size.
WINDOW_MARGIN = 0.1
#: Sampling step of the search region [px].
STRIDE = 2
#: Relative change of the dark area beyond which a frame's centroid is not trusted.
AREA_TOLERANCE = 0.1
#: Edge points the hub is tracked on after the first frame (spread along the dark mask's edges).
EDGE_POINTS = 96
#: Half-length of each edge profile [px]: the most the camera may move between frames before
#: the frame falls back to the centroid.
EDGE_REACH = 8
#: Shortest edge (contour) used, and fewest edge points for tracking [px, points].
EDGE_MIN_CONTOUR = 60
EDGE_MIN_POINTS = 20
#: Share of the edge points that must be found and agree on the shift, else the centroid.
EDGE_AGREE = 0.5
#: Edges off the common shift by more than this many times the median residual (or
#: EDGE_OUTLIER_MIN_PX) are dropped.
EDGE_OUTLIER_MAD = 6.0
EDGE_OUTLIER_MIN_PX = 0.3
#: The profiles are read again around the solved position when it lies this far from the guess.
EDGE_REREAD_PX = 4
#: Spread of the measured offsets below which the camera counts as still [px]: the offsets are
#: then not applied (they would only add the tracker's own jitter).
STILL_CAMERA_PX = 0.1


class HubTracker:
    """The hub's position in each frame: from the wheel's dark parts.

    The first frame takes the centroid of the dark mask (:meth:`centroid`) and picks, on the
    edges of that mask, up to :data:`EDGE_POINTS` points with their normals. Every later frame
    reads only short profiles across those edges (:data:`EDGE_REACH` px either side, along the
    image axis nearest the normal), finds where each crosses the same darkness threshold with
    sub-pixel interpolation, and solves for the shift of the whole shape by least squares,
    dropping edges that moved unlike the rest (a spoke or the marker passing, a hand). A few
    thousand pixels a frame instead of the whole region, and about ten times more precise than
    the centroid (0.03 px against 0.3 px RMS on a render shaking by 1.5 px); when too few
    edges agree (the view changed), the frame falls back to the centroid.

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
        self._edges: _Edges | None = None
        #: Frames measured on the edges, and those that fell back to the centroid.
        self.edge_frames = 0
        self.centroid_frames = 0

    def __call__(self, frame: np.ndarray) -> tuple[float, float, float]:
        """``(x [px], y [px], dark area [px^2])`` of one BGR frame (NaN when nothing is dark).

        On edge-tracked frames the area is the first frame's (at least half the edges agreed
        on the shift); a frame left to the centroid gives its own."""
        edges = self._edges
        if edges is not None:
            hub = edges.track(frame, self.threshold)
            if hub is not None:
                self.edge_frames += 1
                return hub
        hub = self.centroid(frame)
        self.centroid_frames += 1
        if edges is None:
            if math.isfinite(hub[0]) and self._edges is None:
                self._edges = _Edges.anchor(frame, (self.x0, self.y0, self.x1, self.y1),
                                            self.threshold, hub)
        elif math.isfinite(hub[0]):
            edges.shift = (hub[0] - edges.hub0[0], hub[1] - edges.hub0[1])
        return hub

    def many(self, frames: list[np.ndarray]) -> list[tuple[float, float, float]]:
        """:meth:`__call__` on a run of consecutive frames, the edges read for all at once
        (about a fifth of the calls per frame; every frame of the run starts from the shift
        of the frame before the run)."""
        out = []
        i = 0
        while i < len(frames) and self._edges is None:
            out.append(self(frames[i]))
            i += 1
        edges = self._edges
        if i == len(frames) or edges is None:
            return out
        for frame, hub in zip(frames[i:], edges.track_many(frames[i:], self.threshold),
                              strict=True):
            if hub is None:
                hub = self.centroid(frame)
                self.centroid_frames += 1
                if math.isfinite(hub[0]):
                    edges.shift = (hub[0] - edges.hub0[0], hub[1] - edges.hub0[1])
            else:
                self.edge_frames += 1
            out.append(hub)
        return out

    def centroid(self, frame: np.ndarray) -> tuple[float, float, float]:
        """The centroid of the dark mask of the whole (widened) region, on every second pixel:
        ``(x [px], y [px], dark area [px^2])``, NaN when nothing is dark."""
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


class _Edges:
    """Short profiles across the dark mask's edges of one frame, and the shift that carries
    them to another frame (see :class:`HubTracker`).

    A profile along x (y) read ``(dx, dy)`` whole pixels away from where it was on the first
    frame, on a scene shifted by ``(sx, sy)``, crosses the edge ``a0 (sx - dx) + a1 (sy - dy)``
    px from its first crossing (``a = (1, ny / nx)`` along x, ``(nx / ny, 1)`` along y, for the
    edge's normal ``n``): a linear system in the shift, two unknowns for many edges.
    """

    def __init__(self, frame_shape, rows: np.ndarray, cols: np.ndarray, sign: np.ndarray,
                 horiz: np.ndarray, slope: np.ndarray, hub0: tuple[float, float, float]) -> None:
        h, w = frame_shape[:2]
        self.h, self.w = h, w
        # Flat byte index of each profile sample's blue, green and red, first frame.
        pix = 3 * (rows * w + cols)
        # A last sample repeated: "light after all samples" then reads a defined (dark) value.
        pix = np.column_stack([pix, pix[:, -1]])
        self.idx = np.stack([pix, pix + 1, pix + 2])
        # The same, sample-major (3, samples, profiles), for runs of frames: counting the dark
        # samples of every profile then adds whole rows (a tenth of counting along each one).
        idx_t = self.idx.transpose(0, 2, 1)
        # ... counted from the lowest: a frame is read from a view starting there (no indices
        # shifted per frame; in bounds by construction, so unchecked).
        self.idx_t_base = int(idx_t.min())
        self.idx_t = np.ascontiguousarray(idx_t - self.idx_t_base)
        self.row_start = np.arange(rows.shape[0]) * pix.shape[1]
        self.safe = (-int(rows.min()), h - 1 - int(rows.max()),
                     -int(cols.min()), w - 1 - int(cols.max()))
        self.rows_lo, self.rows_hi = rows.min(axis=1), rows.max(axis=1)
        self.cols_lo, self.cols_hi = cols.min(axis=1), cols.max(axis=1)
        self.sign = sign.astype(float)
        self.a = np.vstack([np.where(horiz, 1.0, slope), np.where(horiz, slope, 1.0)])
        a0, a1 = self.a
        self.normal = np.vstack([a0 * a0, a0 * a1, a1 * a1])
        self.hub0 = hub0
        #: First-frame crossing of each profile, as ``sign * (index + fraction)``.
        self.ref = np.zeros(rows.shape[0])
        self.level0 = 1.0
        self.shift = (0.0, 0.0)

    @classmethod
    def anchor(cls, frame: np.ndarray, box: tuple[int, int, int, int], threshold: float,
               hub0: tuple[float, float, float]) -> _Edges | None:
        """Edge points of the dark mask in ``box`` of the first frame; None when too few."""
        import cv2

        x0, y0, x1, y1 = box
        win = frame[y0:y1, x0:x1]
        t = min(254, round(threshold))
        mask = cv2.inRange(win, (0, 0, 0), (t, t, t))
        contours, _ = cv2.findContours(mask, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
        pts = [c.reshape(-1, 2) for c in contours if len(c) >= EDGE_MIN_CONTOUR]
        if not pts:
            return None
        step = max(1, sum(len(p) for p in pts) // EDGE_POINTS)
        xy = np.concatenate([p[::step] for p in pts]).astype(np.int64)
        r = EDGE_REACH
        h, w = mask.shape
        xy = xy[(xy[:, 0] >= r + 2) & (xy[:, 0] < w - r - 2) & (xy[:, 1] >= r + 2)
                & (xy[:, 1] < h - r - 2)]
        # Normals from the gradient of the smoothed darkness (the largest channel: a pixel is
        # dark when all three are), pointing from dark to light: a 5x5 Gaussian blur (sigma
        # 1.2 px) then a 3x3 Sobel derivative, as one 7x7 kernel applied at the points only
        # (the same values as filtering the whole window to rounding, a hundredth of the cost).
        if xy.shape[0] < EDGE_MIN_POINTS:
            return None
        gx, gy = _gradient_at(win, xy)
        mag = np.hypot(gx, gy)
        ok = mag > 1e-3
        xy, gx, gy, mag = xy[ok], gx[ok], gy[ok], mag[ok]
        if xy.shape[0] < EDGE_MIN_POINTS:
            return None
        nx, ny = gx / mag, gy / mag
        # Each profile runs along the image axis nearest its normal, from dark to light.
        horiz = np.abs(nx) >= np.abs(ny)
        sign = np.where(horiz, np.sign(nx), np.sign(ny)).astype(np.int64)
        u = np.arange(-r, r + 1)
        fx, fy = (xy[:, 0] + x0)[:, None], (xy[:, 1] + y0)[:, None]
        rows = np.where(horiz[:, None], fy, fy + sign[:, None] * u)
        cols = np.where(horiz[:, None], fx + sign[:, None] * u, fx)
        # The edge's slope against the profile: a profile read one row (column) off moves the
        # crossing by this much along it.
        slope = np.where(horiz, ny / np.where(horiz, nx, 1.0), nx / np.where(horiz, 1.0, ny))
        edges = cls(frame.shape, rows, cols, sign, horiz, slope, hub0)
        pos, valid, level = edges._crossings(frame, 0, 0, 0.0, float(t))
        if valid.sum() < EDGE_MIN_POINTS:
            return None
        keep = np.flatnonzero(valid)
        edges = cls(frame.shape, rows[keep], cols[keep], sign[keep], horiz[keep], slope[keep],
                    hub0)
        edges.ref, edges.level0 = pos[keep], max(level, 1.0)
        return edges

    def _crossings(self, frame: np.ndarray, dx: int, dy: int, threshold: float,
                   t: float | None = None) -> tuple[np.ndarray, np.ndarray, float]:
        """Where each profile, read ``(dx, dy)`` whole pixels off, crosses the darkness
        threshold, as ``sign * (index + fraction)``; whether it does; and the profiles' mean
        brightness (the light level).

        The crossing is taken after the profile's dark samples (a profile runs from dark to
        light); a profile that is not dark then light there (another edge within reach, a
        spoke) is not found or, if it happens to cross there, is left to the outlier test."""
        import cv2

        h, w = self.h, self.w
        lo_r, hi_r, lo_c, hi_c = self.safe
        idx = self.idx + 3 * (dy * w + dx) if dx or dy else self.idx
        inside = None
        if not (lo_r <= dy <= hi_r and lo_c <= dx <= hi_c):
            inside = ((self.rows_lo + dy >= 0) & (self.rows_hi + dy < h)
                      & (self.cols_lo + dx >= 0) & (self.cols_hi + dx < w))
            idx = np.where(inside[:, None], idx, 0)
        v = frame.reshape(-1).take(idx).max(axis=0)  # dark: all three channels low
        level = cv2.sumElems(v)[0] / v.size
        if t is None:
            # The threshold follows the light (exposure, flicker), as the centroid's does.
            t = threshold * level / self.level0
        k = np.count_nonzero(v[:, :-1] <= t, axis=1)  # samples 0..k-1 dark, k light
        flat = v.ravel()
        at = self.row_start + k  # sample k, the first light one (a pad column when none)
        light = flat.take(at).astype(np.float64)
        dark = flat.take(at - 1)
        valid = (light > t) & (dark <= t) & (k > 0)
        if inside is not None:
            valid &= inside
        pos = self.sign * (k + (t - dark) / np.maximum(light - dark, 1.0))
        return pos, valid, level

    def _solve(self, d: np.ndarray, good: np.ndarray) -> np.ndarray | None:
        """Least-squares shift ``(sx, sy)`` [px] of the edges in ``good``; None when singular."""
        wgt = good.astype(np.float64)
        m00, m01, m11 = self.normal @ wgt
        b0, b1 = (self.a * d) @ wgt
        det = m00 * m11 - m01 * m01
        if not det > 1e-6 * (m00 + m11) ** 2:
            return None
        return np.array([(m11 * b0 - m01 * b1) / det, (m00 * b1 - m01 * b0) / det])

    def track(self, frame: np.ndarray, threshold: float) -> tuple[float, float, float] | None:
        """The hub in this frame from the edges' shift; None when too few edges agree."""
        n = self.ref.size
        least = EDGE_AGREE * n
        sx, sy = self.shift
        for _ in range(2):
            dx, dy = round(sx), round(sy)
            pos, valid, _ = self._crossings(frame, dx, dy, threshold)
            if valid.sum() < least:
                return None
            d = pos - self.ref  # the shift beyond (dx, dy), seen along each profile
            s = self._solve(d, valid)
            if s is None:
                return None
            # Drop the edges that moved unlike the others (a spoke, the marker, a hand), once.
            res = np.abs(s @ self.a - d)
            res_valid = res[valid]
            mid = res_valid.size // 2
            cut = max(EDGE_OUTLIER_MAD * float(np.partition(res_valid, mid)[mid]),
                      EDGE_OUTLIER_MIN_PX)
            good = valid & (res <= cut)
            if good.sum() < least:
                return None
            s = self._solve(d, good)
            if s is None:
                return None
            sx, sy = dx + float(s[0]), dy + float(s[1])
            # Read again around the new position when the guess was far off (the profiles'
            # slope correction is linear).
            if abs(sx - dx) <= EDGE_REREAD_PX and abs(sy - dy) <= EDGE_REREAD_PX:
                break
        if abs(sx - dx) > EDGE_REACH - 2 or abs(sy - dy) > EDGE_REACH - 2:
            return None  # beyond what the profiles can see: the centroid decides
        self.shift = (sx, sy)
        x0, y0, area = self.hub0
        # The first frame's dark area: this frame is vouched for by the edges that agree (a
        # frame where too few do was left to the centroid, whose area then tells).
        return (x0 + sx, y0 + sy, area)


    def track_many(self, frames: list[np.ndarray], threshold: float
                   ) -> list[tuple[float, float, float] | None]:
        """:meth:`track` on a run of frames, their edges read and solved all at once: first
        around the shift before the run, then, for the frames found far from it, around their
        own (as :meth:`track` reads again); a frame left in doubt (too few edges agree, beyond
        the profiles' reach) is tracked on its own, and None where that fails too (the caller
        falls back to the centroid)."""
        nb = len(frames)
        if nb < 2:
            return [self.track(f, threshold) for f in frames]
        guess = np.empty((nb, 2), dtype=np.int64)
        guess[:] = (round(self.shift[0]), round(self.shift[1]))  # (np.round's halves to even)
        s, fine = self._solve_frames(frames, guess, threshold)
        far = fine & (np.abs(s).max(axis=1) > EDGE_REREAD_PX)
        if far.any():
            j = np.flatnonzero(far)
            guess2 = guess[j] + np.round(s[j]).astype(np.int64)
            s2, fine2 = self._solve_frames([frames[i] for i in j], guess2, threshold)
            guess[j], s[j] = guess2, s2
            fine[j] = fine2 & (np.abs(s2).max(axis=1) <= EDGE_REACH - 2)
        x0, y0, area = self.hub0
        out: list[tuple[float, float, float] | None] = []
        for j, frame in enumerate(frames):
            if fine[j]:
                self.shift = (int(guess[j, 0]) + float(s[j, 0]), int(guess[j, 1]) + float(s[j, 1]))
                out.append((x0 + self.shift[0], y0 + self.shift[1], area))
            else:
                out.append(self.track(frame, threshold))
        return out

    def _solve_frames(self, frames: list[np.ndarray], guess: np.ndarray, threshold: float
                      ) -> tuple[np.ndarray, np.ndarray]:
        """The shift of each frame beyond its whole-pixel ``guess`` (B, 2) [px], as
        :meth:`track`'s one reading, and whether it is sound (enough edges agree, solvable,
        profiles inside the frame)."""
        nb = len(frames)
        n = self.ref.size
        width = self.idx.shape[2]
        lo_r, hi_r, lo_c, hi_c = self.safe
        inside = ((guess[:, 1] >= lo_r) & (guess[:, 1] <= hi_r) & (guess[:, 0] >= lo_c)
                  & (guess[:, 0] <= hi_c))
        offset = 3 * (np.where(inside, guess[:, 1], 0) * self.w + np.where(inside, guess[:, 0], 0))
        # (B, samples, profiles): the samples' largest channel.
        v3 = np.empty((nb, *self.idx_t.shape), dtype=np.uint8)
        for j, (f, o) in enumerate(zip(frames, offset, strict=True)):
            f.reshape(-1)[self.idx_t_base + int(o):].take(self.idx_t, out=v3[j], mode="clip")
        v = v3.max(axis=1)
        # The mean brightness (an integer sum: the same number as .mean(), sooner).
        level = np.add.reduce(v.reshape(nb, -1), axis=1, dtype=np.int64) / (v.size // nb)
        t = threshold * level[:, None] / self.level0  # (B, 1), as in _crossings
        k = np.add.reduce(v[:, :-1, :] <= t[:, :, None], axis=1, dtype=np.intp)
        at = k * n + np.arange(n) + (np.arange(nb) * (n * width))[:, None]
        flat = v.ravel()
        light = flat.take(at).astype(np.float64)
        dark = flat.take(at - n)
        valid = (light > t) & (dark <= t) & (k > 0)
        d = self.sign * (k + (t - dark) / np.maximum(light - dark, 1.0)) - self.ref
        least = EDGE_AGREE * n
        s, ok = self._solve_many(d, valid)
        # Drop the edges that moved unlike the others, once, as track does.
        res = np.abs(s @ self.a - d)
        nvalid = valid.sum(axis=1)
        mid = np.sort(np.where(valid, res, np.inf), axis=1)[np.arange(nb), nvalid // 2]
        cut = np.maximum(EDGE_OUTLIER_MAD * mid, EDGE_OUTLIER_MIN_PX)
        good = valid & (res <= cut[:, None])
        s2, ok2 = self._solve_many(d, good)
        fine = inside & ok & ok2 & (nvalid >= least) & (good.sum(axis=1) >= least)
        return s2, fine

    def _solve_many(self, d: np.ndarray, good: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_solve` for each row of ``d`` (B, N): shifts (B, 2) and whether solvable."""
        wgt = good.astype(np.float64)
        m00, m01, m11 = (wgt @ self.normal.T).T
        b0, b1 = ((d * wgt) @ self.a.T).T
        det = m00 * m11 - m01 * m01
        ok = det > 1e-6 * (m00 + m11) ** 2
        det = np.where(ok, det, 1.0)
        return np.column_stack([(m11 * b0 - m01 * b1) / det, (m00 * b1 - m01 * b0) / det]), ok


def _gradient_kernels() -> tuple[np.ndarray, np.ndarray]:
    """The 7-tap factors of a 5x5 Gaussian blur (sigma 1.2 px) followed by a 3x3 Sobel
    derivative: ``(derivative, smoothing)``; x derivative = smoothing (rows) x derivative
    (columns), y the other way round (OpenCV's kernels, correlation order)."""
    import cv2

    g = cv2.getGaussianKernel(5, 1.2).ravel()
    return np.convolve([-1.0, 0.0, 1.0], g), np.convolve([1.0, 2.0, 1.0], g)


def _gradient_at(win: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gradient ``(gx, gy)`` of the blurred largest channel of ``win`` (BGR) at integer points
    ``xy`` (N, 2) at least 3 px inside it: what ``cv2.Sobel(cv2.GaussianBlur(bright, (5, 5),
    1.2))`` gives there (interior points: no border rule involved)."""
    deriv, smooth = _gradient_kernels()
    off = np.arange(-3, 4)
    rows = xy[:, 1, None, None] + off[None, :, None]
    cols = xy[:, 0, None, None] + off[None, None, :]
    bright = win[rows, cols].max(axis=3).astype(np.float64)  # (N, 7, 7)
    gx = np.einsum("nij,i,j->n", bright, smooth, deriv)
    gy = np.einsum("nij,i,j->n", bright, deriv, smooth)
    return gx, gy


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
