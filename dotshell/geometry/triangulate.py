"""Ray–plane triangulation of camera pixels against projector stripe planes.

For a decoded projector column u, the lit points form a plane through the projector centre:
in the projector frame, all points whose ideal (undistorted) normalized x equals x_u. A camera
ray through the pixel meets that plane at one point. Projector lens distortion bends the plane
slightly; it is handled exactly when the projector row is decoded too, and by a fixed-point
iteration on the predicted row otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from dotshell.geometry.calibration import RigCalibration
from dotshell.geometry.lens import Lens


@dataclass
class Triangulation:
    """Result for N input pixels.

    Attributes:
        points: (N, 3) camera-frame points in mm (NaN where not kept).
        keep: (N,) bool, points that passed every check.
        row_rejected: (N,) bool, dropped by the row consistency check.
        grazing: (N,) bool, dropped because ray and plane meet too obliquely.
    """

    points: np.ndarray
    keep: np.ndarray
    row_rejected: np.ndarray
    grazing: np.ndarray


@lru_cache(maxsize=4)
def _ray_grid(key: tuple) -> np.ndarray:
    K, dist, w, h = key
    lens = Lens(np.array(K).reshape(3, 3), np.array(dist), w, h)
    ys, xs = np.mgrid[0:h, 0:w]
    px = np.column_stack([xs.ravel(), ys.ravel()]).astype(np.float64)
    n = lens.undistort(px)
    return np.column_stack([n, np.ones(len(n))]).reshape(h, w, 3)


def camera_ray_grid(lens: Lens) -> np.ndarray:
    """(H, W, 3) un-normalized ray directions (x_n, y_n, 1) for every camera pixel centre."""
    key = (tuple(lens.K.ravel()), tuple(lens.dist), lens.width, lens.height)
    return _ray_grid(key)


def triangulate(rays: np.ndarray, column: np.ndarray, calib: RigCalibration,
                row: np.ndarray | None = None, row_tolerance_px: float = 1.5,
                min_ray_angle_deg: float = 5.0, iterations: int = 3) -> Triangulation:
    """Intersect camera rays with projector column planes.

    Args:
        rays: (N, 3) camera-frame ray directions through the pixels (any length).
        column: (N,) decoded projector columns (pixels, sub-pixel allowed).
        calib: rig calibration.
        row: (N,) decoded projector rows, or None for column-only codings.
        row_tolerance_px: rows predicted from the point must match decoded rows this closely.
        min_ray_angle_deg: minimum angle between ray and plane.
        iterations: fixed-point iterations for projector distortion without rows.
    """
    proj = calib.projector
    n = len(column)
    col = np.asarray(column, np.float64)
    guess_row = np.full(n, proj.K[1, 2]) if row is None else np.asarray(row, np.float64)
    pts = np.full((n, 3), np.nan)
    sin_angle = np.zeros(n)
    for _ in range(1 if row is not None else iterations):
        ideal = proj.undistort(np.column_stack([col, guess_row]))
        normal_p = np.column_stack([np.ones(n), np.zeros(n), -ideal[:, 0]])  # plane in proj frame
        normal_c = normal_p @ calib.R  # (R^T n_p) as rows
        offset = normal_p @ calib.T
        denom = np.einsum("ij,ij->i", normal_c, rays)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = -offset / denom
        pts = rays * s[:, None]
        sin_angle = np.abs(denom) / (np.linalg.norm(normal_c, axis=1) * np.linalg.norm(rays, axis=1))
        if row is None:
            predicted = proj.project(np.where(np.isfinite(pts), pts, 0.0) @ calib.R.T + calib.T)
            guess_row = predicted[:, 1]
    grazing = sin_angle < np.sin(np.deg2rad(min_ray_angle_deg))
    ok = np.isfinite(pts).all(axis=1) & (pts[:, 2] > 0) & ~grazing
    row_rejected = np.zeros(n, bool)
    if row is not None:
        predicted = proj.project(np.where(ok[:, None], pts, 1.0) @ calib.R.T + calib.T)
        row_rejected = ok & (np.abs(predicted[:, 1] - row) > row_tolerance_px)
        ok &= ~row_rejected
    pts[~ok] = np.nan
    return Triangulation(pts, ok, row_rejected, grazing)
