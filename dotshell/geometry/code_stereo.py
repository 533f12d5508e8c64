"""Camera–camera triangulation through projector codes (pure; mm, pixels).

Two cameras that see one projector's sequence decode, per pixel, the projector column and row
that lit it. Where both cameras decoded the same projector coordinate they look at the same
surface point: the codes are only the correspondence, so the projector need not be calibrated.
:func:`match_by_codes` finds, for every decoded pixel of camera 1, the sub-pixel position in
camera 2 with the same (column, row) — a linear interpolation of camera 2's decoded pixels over
projector coordinates, refused across gaps (occlusion edges) — and :func:`triangulate_pair`
intersects the two rays.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import LinearNDInterpolator

from dotshell.geometry.lens import Lens

#: A match is refused when camera 2's pixels around it (the interpolation triangle) lie
#: further apart than this (px): the triangle spans a gap in camera 2's view.
MAX_SPAN_PX = 3.0


def match_by_codes(col1: np.ndarray, row1: np.ndarray, valid1: np.ndarray, col2: np.ndarray,
                   row2: np.ndarray, valid2: np.ndarray,
                   max_span_px: float = MAX_SPAN_PX) -> tuple[np.ndarray, np.ndarray]:
    """Camera-1 pixels (N, 2) (x, y) and the camera-2 positions (N, 2) that decoded the same
    projector (column, row), sub-pixel; only where camera 2 saw that coordinate."""
    y2, x2 = np.nonzero(valid2)
    codes2 = np.column_stack([col2[valid2], row2[valid2]]).astype(np.float64)
    if len(codes2) < 3:
        return np.zeros((0, 2)), np.zeros((0, 2))
    interp = LinearNDInterpolator(codes2, np.column_stack([x2, y2]).astype(np.float64))
    y1, x1 = np.nonzero(valid1)
    codes1 = np.column_stack([col1[valid1], row1[valid1]]).astype(np.float64)
    pos2 = interp(codes1)
    simplex = interp.tri.find_simplex(codes1)
    ok = np.isfinite(pos2).all(axis=1) & (simplex >= 0)
    corners = interp.tri.simplices[simplex[ok]]               # (M, 3) vertex indices
    pts = np.column_stack([x2, y2]).astype(np.float64)[corners]  # (M, 3, 2)
    span = np.max(np.linalg.norm(pts - np.roll(pts, 1, axis=1), axis=2), axis=1)
    keep = np.flatnonzero(ok)[span <= max_span_px]
    return np.column_stack([x1, y1])[keep].astype(np.float64), pos2[keep]


def triangulate_pair(lens1: Lens, lens2: Lens, R: np.ndarray, T: np.ndarray,
                     pix1: np.ndarray, pix2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) in camera 1's frame (mm) from matched pixels, with ``X2 = R X1 + T``: the
    midpoint of the two rays' closest approach. Also returns that gap (N,) in mm (a check of
    the match and of the calibration)."""
    d1 = lens1.rays(pix1)
    R = np.asarray(R, float)
    d2 = lens2.rays(pix2) @ R                                  # Rᵀ d in camera 1's frame
    c2 = -R.T @ np.asarray(T, float).ravel()
    b = d1 @ c2.reshape(3), np.einsum("ij,ij->i", d2, np.broadcast_to(c2, d2.shape))
    a12 = np.einsum("ij,ij->i", d1, d2)
    den = 1.0 - a12 ** 2
    den = np.where(den < 1e-12, np.nan, den)
    s = (b[0] - a12 * b[1]) / den                              # along ray 1
    t = (a12 * b[0] - b[1]) / den                              # along ray 2
    p1 = d1 * s[:, None]
    p2 = c2 + d2 * t[:, None]
    return 0.5 * (p1 + p2), np.linalg.norm(p1 - p2, axis=1)
