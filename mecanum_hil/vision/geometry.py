"""The marker's path: a circle seen as an ellipse, found robustly among candidate blobs (pure).

An oblique (affine) view of a wheel turns its rim into an ellipse. The angle of the wheel is taken
after mapping the ellipse back onto a circle: rotate into the ellipse's axes and stretch the
minor axis to the major one. Under an affine view this recovers the wheel angle up to a constant;
a strongly perspective view (camera close to the wheel, wide lens) is only approximately affine.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import VideoError

#: Largest accepted ratio of the ellipse axes (a tilt of about 80 degrees).
MAX_AXIS_RATIO = 6.0


@dataclass(frozen=True)
class Ellipse:
    """An ellipse in the image.

    Attributes
    ----------
    cx_px, cy_px : float
        Centre [px].
    a_px, b_px : float
        Semi-axes [px]: ``a_px`` along ``angle_deg``, ``b_px`` across it.
    angle_deg : float
        Direction of the ``a`` axis [deg], measured as OpenCV does (x right, y down).
    """

    cx_px: float
    cy_px: float
    a_px: float
    b_px: float
    angle_deg: float

    @property
    def tilt_deg(self) -> float:
        """View angle off the wheel axis implied by the axis ratio [deg]."""
        lo, hi = sorted((self.a_px, self.b_px))
        return math.degrees(math.acos(min(1.0, lo / hi)))

    def unit(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Points mapped onto the unit circle: ``(radius ratio, angle [rad])``.

        The angle is counter-clockwise positive as seen in the image (y points down there), up
        to a constant.
        """
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        t = math.radians(self.angle_deg)
        dx = xy[:, 0] - self.cx_px
        dy = xy[:, 1] - self.cy_px
        u = (math.cos(t) * dx + math.sin(t) * dy) / self.a_px
        v = (-math.sin(t) * dx + math.cos(t) * dy) / self.b_px
        return np.hypot(u, v), np.arctan2(-v, u)


def _from_cv(box) -> Ellipse | None:
    (cx, cy), (w, h), ang = box
    if not (all(math.isfinite(v) for v in (cx, cy, w, h, ang)) and w > 0 and h > 0):
        return None
    return Ellipse(float(cx), float(cy), 0.5 * float(w), 0.5 * float(h), float(ang))


def fit_ellipse(xy: np.ndarray) -> Ellipse | None:
    """Least-squares ellipse through points (OpenCV's direct fit); None when degenerate."""
    import cv2

    pts = np.ascontiguousarray(xy, dtype=np.float32).reshape(-1, 1, 2)
    if len(pts) < 5:
        return None
    try:
        return _from_cv(cv2.fitEllipseDirect(pts))
    except cv2.error:
        return None


def fit_circle(xy: np.ndarray) -> Ellipse | None:
    """Least-squares circle through points (algebraic fit); None when degenerate."""
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    if len(xy) < 3:
        return None
    m = xy.mean(axis=0)
    d = xy - m
    A = np.column_stack([d, np.ones(len(d))])
    rhs = (d ** 2).sum(axis=1)
    sol, *_ = np.linalg.lstsq(A, rhs, rcond=None)
    cx, cy = sol[0] / 2, sol[1] / 2
    r2 = sol[2] + cx * cx + cy * cy
    if not r2 > 0:
        return None
    r = math.sqrt(r2)
    return Ellipse(float(cx + m[0]), float(cy + m[1]), r, r, 0.0)


def plausible(e: Ellipse | None, max_radius_px: float, min_radius_px: float = 3.0) -> bool:
    """Whether an ellipse can be a wheel's marker path in a region of this size."""
    if e is None:
        return False
    lo, hi = sorted((e.a_px, e.b_px))
    return lo >= min_radius_px and hi <= max_radius_px and hi / lo <= MAX_AXIS_RATIO


def angular_coverage(angle_rad: np.ndarray) -> float:
    """Share of the full turn spanned by the angles: one minus the largest gap between them."""
    if angle_rad.size < 2:
        return 0.0
    a = np.sort(np.mod(angle_rad, 2 * np.pi))
    # The gaps between neighbours and the one across zero.
    gap = np.maximum(np.diff(a).max(), a[0] + 2 * np.pi - a[-1])
    return float(1.0 - gap / (2 * np.pi))


@dataclass(frozen=True)
class Track:
    """The marker's chosen detections and its path.

    Attributes
    ----------
    path : Ellipse
    xy_px : ndarray, shape (N, 2)
        Marker position per frame [px]; NaN where it was not found.
    found : ndarray of bool, shape (N,)
    coverage : float
        Share of the path's full turn that the marker was seen on (see
        :func:`angular_coverage`).
    shape : str
        ``"ellipse"`` or ``"circle"`` (too little of the path seen to fit an ellipse).
    residual_px : float
        RMS distance of the chosen detections from the path [px] (about the radius times the
        relative radial error): large for a circle fitted to an oblique view's short arc.
    index : ndarray of int, shape (N,), optional
        The chosen candidate of each frame (-1: none).
    """

    path: Ellipse
    xy_px: np.ndarray
    found: np.ndarray
    coverage: float
    shape: str
    residual_px: float = 0.0
    index: np.ndarray | None = None


def _hue_close(h: np.ndarray, h0: float, tol_deg: float) -> np.ndarray:
    d = np.abs((h - h0 + 180.0) % 360.0 - 180.0)
    return d <= tol_deg


def select_track(frame_idx: np.ndarray, xy: np.ndarray, hue_deg: np.ndarray, n_frames: int,
                 max_radius_px: float, rng: np.random.Generator | None = None,
                 hypotheses: int = 400, rho_tol: float = 0.12, hue_tol_deg: float = 25.0,
                 source: str = "video", initial: Ellipse | None = None,
                 hint: str = "give --marker-hsv, or --roi around the wheel") -> Track:
    """Find the candidate blobs that move on a circle (an ellipse in the image).

    RANSAC: ellipses through five candidates of one hue from different places; the winner is the
    one that the most frames have a same-hue candidate on. Static blobs (no circle) and blobs
    moving on a line (degenerate ellipse) lose. The path is then refit on every frame's best
    candidate: an ellipse when the marker visited most of it, else a circle.

    Parameters
    ----------
    frame_idx : ndarray of int, shape (M,)
        Frame of each candidate.
    xy : ndarray, shape (M, 2)
        Candidate centroids [px].
    hue_deg : ndarray, shape (M,)
        Candidate hues [deg].
    n_frames : int
    max_radius_px : float
        Largest plausible path radius [px] (the search region's size).
    initial : Ellipse, optional
        A path found before (on part of the video): the first hypothesis; the search then
        only draws random samples around it.
    hint : str
        What the user can do when no marker is found (the end of the error message).

    Raises
    ------
    VideoError
        No candidate moves on a circle.
    """
    rng = rng or np.random.default_rng(12345)
    if len(frame_idx) < 5:
        raise VideoError(f"{source}: no marker: no saturated blob found in the video "
                         f"({hint})")
    score, path, hue0 = _search_path(frame_idx, xy, hue_deg, n_frames, max_radius_px, rng,
                                     hypotheses, rho_tol, hue_tol_deg, initial)
    if path is None or score < 3:
        raise VideoError(f"{source}: no marker: no saturated blob moves on a circle "
                         f"({hint})")
    path, shape = _refine_path(path, frame_idx, xy, hue_deg, hue0, n_frames, max_radius_px,
                               rho_tol, hue_tol_deg, source)
    track_xy, found, index = _best_per_frame(path, frame_idx, xy, hue_deg, hue0, n_frames,
                                             rho_tol, hue_tol_deg, with_index=True)
    rho, ang = path.unit(track_xy[found])
    residual = float(np.sqrt(np.mean((rho - 1.0) ** 2)) * math.sqrt(path.a_px * path.b_px))
    return Track(path, track_xy, found, angular_coverage(ang), shape, residual, index)


def _search_path(frame_idx: np.ndarray, xy: np.ndarray, hue_deg: np.ndarray, n_frames: int,
                 max_radius_px: float, rng: np.random.Generator, hypotheses: int,
                 rho_tol: float, hue_tol_deg: float, initial: Ellipse | None
                 ) -> tuple[float, Ellipse | None, float]:
    """RANSAC over ellipses through five candidates: ``(score, path, hue [deg])`` of the best
    (``path`` ``None`` when no hypothesis was plausible)."""
    m = len(frame_idx)
    grid = np.round(xy / 2.0).astype(np.int64)
    # Each candidate's 2 px cell, numbered 0..cells-1: distinct cells are then counted by
    # marking them (np.unique's sort, once per hypothesis, cost more than the rest).
    _, cell = np.unique(grid[:, 0] * 1_000_003 + grid[:, 1], return_inverse=True)
    cell = cell.reshape(-1)
    seen = np.zeros(int(cell.max()) + 1 if m else 0, dtype=bool)
    xy32 = xy.astype(np.float32)  # what fit_ellipse hands OpenCV, converted once
    xs = np.ascontiguousarray(xy[:, 0], dtype=float)
    ys = np.ascontiguousarray(xy[:, 1], dtype=float)
    best: tuple[float, Ellipse | None, float] = (-1.0, None, 0.0)
    if initial is not None:
        best = _score_initial(initial, xy, hue_deg, cell, rho_tol, hue_tol_deg, best)
        link = np.full(m, -1)
        moving = np.arange(m)
    else:
        link = _link_frames(frame_idx, xy, hue_deg, n_frames, 0.25 * max_radius_px, hue_tol_deg)
        moving = np.flatnonzero((link >= 0)
                                & (np.hypot(*(xy[np.maximum(link, 0)] - xy).T) > 0.5))
    moving_mask = np.zeros(m, dtype=bool)
    moving_mask[moving] = True
    last_gain = 0
    for h in range(hypotheses):
        if h - last_gain > max(40, hypotheses // 8):
            break  # no better path in a long while: the marker's is found
        # Half the hypotheses follow one blob from frame to frame (five points of one chain),
        # half draw moving blobs of one hue at random (robust when the linking fails).
        # (moving[rng.integers(...)] draws what rng.choice(moving) draws, a fifth of its cost)
        i0 = int(moving[rng.integers(moving.size)]) if moving.size and h % 4 else \
            int(rng.integers(m))
        same_mask = _hue_close(hue_deg, hue_deg[i0], hue_tol_deg)
        same = np.flatnonzero(same_mask)
        if same.size < 5:
            continue
        if h % 2 and initial is None:
            chain = _follow(link, i0, int(rng.integers(5, max(6, min(n_frames, 400)))))
            if len(chain) < 5:
                continue
            # (np.linspace(0, len - 1, 5).astype(int): the quarters are exact in binary)
            last = len(chain) - 1
            pick = np.array([chain[(q * last) // 4] for q in range(5)])
        else:
            # (np.intersect1d(same, moving), without its sort)
            pool = np.flatnonzero(same_mask & moving_mask) if moving.size else same
            pick = rng.choice(pool if pool.size >= 5 else same, 5, replace=False)
        # The five points' extent (in Python floats: numpy's reductions cost more on five).
        px, py = zip(*xy[pick].tolist(), strict=True)
        if (max(px) - min(px)) + (max(py) - min(py)) < 4.0:
            continue
        e = fit_ellipse(xy32[pick])
        if not plausible(e, max_radius_px):
            continue
        # (e.unit(xy[same]), on the coordinates' columns: the same arithmetic, less overhead)
        t = math.radians(e.angle_deg)
        ct, st = math.cos(t), math.sin(t)
        dx = xs[same] - e.cx_px
        dy = ys[same] - e.cy_px
        u = (ct * dx + st * dy) / e.a_px
        v = (-st * dx + ct * dy) / e.b_px
        rho, ang = np.hypot(u, v), np.arctan2(-v, u)
        ok = np.abs(rho - 1.0) < rho_tol
        # Distinct places, not frames: a static blob that happens to lie on a hypothesis counts
        # once, however many frames it is in; times the share of the path visited: a blob
        # sliding along a line sits on a thin ellipse's two ends only.
        seen[:] = False
        seen[cell[same[ok]]] = True
        score = int(np.count_nonzero(seen)) * angular_coverage(ang[ok])
        if score > best[0]:
            if score > 1.05 * best[0]:
                last_gain = h
            best = (score, e, float(hue_deg[i0]))
    return best


def _score_initial(initial: Ellipse, xy: np.ndarray, hue_deg: np.ndarray, cell: np.ndarray,
                   rho_tol: float, hue_tol_deg: float,
                   best: tuple[float, Ellipse | None, float]
                   ) -> tuple[float, Ellipse | None, float]:
    """A path found before as the first hypothesis, scored as the search scores its own."""
    rho, ang = initial.unit(xy)
    on = np.abs(rho - 1.0) < rho_tol
    if on.sum() < 5:
        return best
    hue_init = float(np.median(hue_deg[on]))
    same = _hue_close(hue_deg, hue_init, hue_tol_deg) & on
    return (np.unique(cell[same]).size * angular_coverage(ang[same]), initial, hue_init)


def _refine_path(path: Ellipse, frame_idx: np.ndarray, xy: np.ndarray, hue_deg: np.ndarray,
                 hue0: float, n_frames: int, max_radius_px: float, rho_tol: float,
                 hue_tol_deg: float, source: str) -> tuple[Ellipse, str]:
    """Refit the path on each frame's best candidate, twice: ``(path, "ellipse"|"circle")``."""
    for _ in range(2):  # refit on the chosen detections, then choose again with the refined path
        track_xy, found = _best_per_frame(path, frame_idx, xy, hue_deg, hue0, n_frames, rho_tol,
                                          hue_tol_deg)
        pts = track_xy[found]
        _, ang = path.unit(pts)
        coverage = angular_coverage(ang)
        if coverage < 0.05:
            raise VideoError(f"{source}: the marker does not move (it stays within "
                             f"{360 * coverage:.0f} deg of its path); no speed can be measured")
        shape, refit = _refit(pts, coverage, max_radius_px)
        if refit is not None:
            path = refit
        else:
            shape = "ellipse" if path.a_px != path.b_px else "circle"
    return path, shape


def refit_track(track: Track, max_radius_px: float) -> Track:
    """The path fitted again on the track's found frames only (after some were dropped)."""
    pts = track.xy_px[track.found]
    if len(pts) < 5:
        return track
    _, ang = track.path.unit(pts)
    shape, path = _refit(pts, angular_coverage(ang), max_radius_px)
    if path is None:
        return track
    rho, ang = path.unit(pts)
    residual = float(np.sqrt(np.mean((rho - 1.0) ** 2)) * math.sqrt(path.a_px * path.b_px))
    return Track(path, track.xy_px, track.found, angular_coverage(ang), shape, residual,
                 track.index)


def _refit(pts: np.ndarray, coverage: float, max_radius_px: float
           ) -> tuple[str, Ellipse | None]:
    """Least-squares path through the chosen points: an ellipse when most of it was seen; on a
    shorter arc a circle, unless an ellipse fits far better (an oblique view)."""
    ell = fit_ellipse(pts)
    ell = ell if plausible(ell, max_radius_px) else None
    if coverage >= 0.6:
        return "ellipse", ell
    circ = fit_circle(pts)
    circ = circ if plausible(circ, max_radius_px) else None
    if circ is None or ell is None:
        return ("circle", circ) if circ is not None else ("ellipse", ell)

    def rms_px(e: Ellipse) -> float:
        rho, _ = e.unit(pts)
        return float(np.sqrt(np.mean((rho - 1.0) ** 2)) * math.sqrt(e.a_px * e.b_px))

    r_c, r_e = rms_px(circ), rms_px(ell)
    # An ellipse has two more parameters: it must beat the circle clearly to be believed.
    if r_c > 0.15 and r_e < 0.5 * r_c:
        return "ellipse", ell
    return "circle", circ


#: Hue range around the path's first-found hue within which a blob may be the marker before its
#: hue is followed along the video [deg] (the marker's colour shifts under changing light).
HUE_DRIFT_TOL_DEG = 60.0
#: Found frames over which the marker's hue is followed (a running median).
HUE_FOLLOW_FRAMES = 31


def _pick(err, ok, frame_idx, n_frames):
    """Each frame's candidate in ``ok`` with the smallest finite ``err`` (the first of equals),
    -1 where none."""
    index = np.full(n_frames, -1)
    sel = np.flatnonzero(ok & (err < np.inf))
    if sel.size:
        # By frame, then error, then candidate: each frame's first is its pick.
        order = sel[np.lexsort((sel, err[sel], frame_idx[sel]))]
        frames = frame_idx[order]
        first = np.r_[True, frames[1:] != frames[:-1]]
        index[frames[first]] = order[first]
    return index


def _best_per_frame(path, frame_idx, xy, hue_deg, hue0, n_frames, rho_tol, hue_tol,
                    with_index=False):
    """Each frame's candidate nearest the path among those of the marker's hue.

    The hue is followed along the video: first candidates within :data:`HUE_DRIFT_TOL_DEG` of
    ``hue0``, then within ``hue_tol`` of the running median of those chosen.
    """
    rho, _ = path.unit(xy)
    err = np.abs(rho - 1.0)
    near = err < rho_tol
    index = _pick(err, near & _hue_close(hue_deg, hue0, HUE_DRIFT_TOL_DEG), frame_idx, n_frames)
    found = index >= 0
    if found.sum() >= 3:
        rel = (hue_deg[index[found]] - hue0 + 180.0) % 360.0 - 180.0
        k = min(HUE_FOLLOW_FRAMES, rel.size) | 1
        padded = np.pad(rel, k // 2, mode="edge")
        med = np.median(np.lib.stride_tricks.sliding_window_view(padded, k), axis=1)
        frames = np.flatnonzero(found)
        local = hue0 + np.interp(np.arange(n_frames), frames, med)
        d = np.abs((hue_deg - local[frame_idx] + 180.0) % 360.0 - 180.0)
        index = _pick(err, near & (d <= hue_tol), frame_idx, n_frames)
        found = index >= 0
    track = np.full((n_frames, 2), np.nan)
    track[found] = xy[index[found]]
    if with_index:
        return track, found, index
    return track, found


def _link_frames(frame_idx, xy, hue_deg, n_frames, max_step_px, hue_tol) -> np.ndarray:
    """For each candidate, its nearest same-hue candidate in the next frame (-1: none)."""
    link = np.full(len(frame_idx), -1, dtype=int)
    order = np.argsort(frame_idx, kind="stable")
    starts = np.searchsorted(frame_idx[order], np.arange(n_frames + 1))
    # Frames with one candidate followed by a frame with one (the marker alone, the usual case):
    # all at once, by the same arithmetic as the loop below.
    counts = np.diff(starts)
    single = (counts[:-1] == 1) & (counts[1:] == 1)
    fs = np.flatnonzero(single)
    ia, ib = order[starts[fs]], order[starts[fs + 1]]
    d = np.hypot(xy[ia, 0] - xy[ib, 0], xy[ia, 1] - xy[ib, 1])
    dh = np.abs((hue_deg[ia] - hue_deg[ib] + 180.0) % 360.0 - 180.0)
    ok = ~(dh > hue_tol) & (d <= max_step_px)
    link[ia[ok]] = ib[ok]
    # The other pairs of frames all at once too: each frame's candidates padded to the most any
    # frame has (the padding never nearest), the same arithmetic per pair as the singles'.
    fm = np.flatnonzero(~single & (counts[:-1] > 0) & (counts[1:] > 0))
    if fm.size == 0:
        return link
    width = int(max(counts[fm].max(), counts[fm + 1].max()))
    k = np.arange(width)

    def members(frames):
        pos = starts[frames][:, None] + k
        real = k < counts[frames][:, None]
        return order[np.where(real, pos, 0)], real

    a, a_real = members(fm)
    b, b_real = members(fm + 1)
    d = np.hypot(xy[a, 0][:, :, None] - xy[b, 0][:, None, :],
                 xy[a, 1][:, :, None] - xy[b, 1][:, None, :])
    dh = np.abs((hue_deg[a][:, :, None] - hue_deg[b][:, None, :] + 180.0) % 360.0 - 180.0)
    d[(dh > hue_tol) | ~b_real[:, None, :]] = np.inf
    j = np.argmin(d, axis=2)
    ok = a_real & (np.take_along_axis(d, j[:, :, None], axis=2)[:, :, 0] <= max_step_px)
    link[a[ok]] = np.take_along_axis(b, j, axis=1)[ok]
    return link


def _follow(link: np.ndarray, start: int, length: int) -> list[int]:
    chain = [start]
    while len(chain) < length and link[chain[-1]] >= 0:
        chain.append(int(link[chain[-1]]))
    return chain
