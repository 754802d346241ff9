"""ArUco markers: the wheel angle from one marker's orientation per frame.

The marker is fixed on the wheel (anywhere: centred on the hub is best, it need not move on a
circle). Its four corners are found with OpenCV's ``cv2.aruco`` (sub-pixel corner refinement). The
marker's two edge vectors form a 2x2 matrix ``A_k = s V R(theta_k)``: a fixed view distortion
``V`` (an oblique, affine view), the scale ``s`` and the wheel's rotation. Since
``A_k A_k^T = s^2 V V^T`` does not depend on the rotation, its average over the video gives
``W = (V V^T)^(1/2)``; ``W^-1 A_k`` is then a pure rotation (up to a constant), whose angle is the
wheel angle, counter-clockwise in the image positive.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import VideoError
from .detect import clip_roi

#: The dictionary markers are looked up in (and the renderer draws from).
DICTIONARY = "DICT_4X4_50"


def aruco_dictionary():
    """OpenCV's predefined :data:`DICTIONARY`."""
    import cv2

    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, DICTIONARY))


class ArucoDetector:
    """Find ArUco markers in one region of each frame.

    Each call returns rows ``(id, x0, y0, x1, y1, x2, y2, x3, y3)``: the marker's corners [px]
    in OpenCV's order (top-left, top-right, bottom-right, bottom-left of the marker itself).
    """

    def __init__(self, roi: tuple[int, int, int, int] | None,
                 frame_size: tuple[int, int]) -> None:
        import cv2

        self.x0, self.y0, self.x1, self.y1 = clip_roi(roi, frame_size)
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        self._detector = cv2.aruco.ArucoDetector(aruco_dictionary(), params)

    def __call__(self, frame: np.ndarray) -> np.ndarray:
        import cv2

        crop = frame[self.y0:self.y1, self.x0:self.x1]
        gray = cv2.cvtColor(crop, cv2.COLOR_BGR2GRAY)
        corners, ids, _ = self._detector.detectMarkers(gray)
        if ids is None or len(ids) == 0:
            return np.empty((0, 9))
        offset = np.array([self.x0, self.y0], dtype=float)
        rows = [np.concatenate([[float(i)], (c.reshape(4, 2) + offset).ravel()])
                for c, i in zip(corners, ids.ravel(), strict=True)]
        return np.array(rows, dtype=float)


def aruco_angles(cands: list[np.ndarray], source: str = "video") -> tuple[np.ndarray, dict]:
    """Wheel angle per frame [rad] (NaN where the marker was not seen) and a summary.

    The marker is the id seen in the most frames.

    Raises
    ------
    VideoError
        No ArUco marker in any frame.
    """
    n = len(cands)
    ids = np.concatenate([np.empty(0)] + [c[:, 0] for c in cands if len(c)])
    if ids.size == 0:
        raise VideoError(f"{source}: no marker: no ArUco marker ({DICTIONARY}) found in the "
                         "video")
    values, counts = np.unique(ids, return_counts=True)
    marker_id = values[int(np.argmax(counts))]
    A = np.full((n, 2, 2), np.nan)
    for k, c in enumerate(cands):
        hit = c[c[:, 0] == marker_id] if len(c) else c
        if len(hit):
            p = hit[0, 1:].reshape(4, 2)
            # Edge vectors averaged over the two opposite sides: the marker's x and y axes.
            ex = 0.5 * ((p[1] - p[0]) + (p[2] - p[3]))
            ey = 0.5 * ((p[3] - p[0]) + (p[2] - p[1]))
            A[k] = np.column_stack([ex, ey])
    found = np.isfinite(A[:, 0, 0])
    G = np.einsum("kij,klj->il", A[found], A[found]) / found.sum()
    evals, evecs = np.linalg.eigh(G)
    if not evals.min() > 0:
        raise VideoError(f"{source}: the ArUco marker's outline is degenerate")
    W_inv = evecs @ np.diag(evals ** -0.5) @ evecs.T
    Q = np.einsum("ij,kjl->kil", W_inv, A[found])
    angle = np.full(n, np.nan)
    # Q = R(theta) with R(theta) = [[cos, sin], [-sin, cos]]: counter-clockwise on screen.
    angle[found] = np.arctan2(Q[:, 0, 1] - Q[:, 1, 0], Q[:, 0, 0] + Q[:, 1, 1])
    tilt = math.degrees(math.acos(min(1.0, math.sqrt(evals.min() / evals.max()))))
    return angle, {"path": "aruco", "marker_id": int(marker_id),
                   "view_tilt_deg": round(tilt, 1)}
