"""Triangulation of camera pixels against the projector's stripe planes.

A decoded projector column u is a plane through the projector centre (all points whose ideal,
undistorted normalized projector x equals x_u); a decoded row v likewise a plane (ideal y = y_v).
The point lies on the camera ray through the pixel.

* **Both codes** (column and row decoded): the point on the camera ray that best satisfies the
  column plane and the row plane together, in the least-squares sense of the projector
  reprojection error. Along the ray (``X = s·r``), plane ``i`` is the linear equation
  ``a_i s + b_i = 0``; its residual, divided by the projector depth, is the reprojection
  error in ideal normalized coordinates, so ``f_i² (a_i s + b_i)²`` (f the projector focal
  length of that axis, px) is the squared error in projector pixels and
  ``s = −Σ f_i² a_i b_i / Σ f_i² a_i²``. ``|a_i|`` is how steeply the ray crosses plane ``i``:
  a decoding error of δ px moves the point along the ray by ``δ / (f_i |a_i|)``, so each plane
  is weighted by how well it conditions depth (inverse variance). A plane the ray grazes (the
  rows of a horizontal baseline, the columns of a vertical one) gets almost no weight, and any
  baseline direction — beside, above or diagonal to the camera — triangulates alike. Lens
  distortion of the projector is undone exactly (column and row known).
  ``grazing``: the camera ray and the projector ray through (u, v) meet at less than
  ``min_ray_angle_deg``. ``row_rejected``: the decoded column and row do not meet at one point —
  the point reprojects more than ``row_tolerance_px`` from (u, v), i.e. the code that does not
  set the depth lies off the epipolar line.
* **Columns only**: the camera ray meets the column plane; projector distortion bends the plane
  slightly and is handled by a fixed-point iteration on the predicted row. ``grazing``: the ray
  meets the plane at less than ``min_ray_angle_deg`` (always the case when the projector is
  above or below the camera: decode rows then).
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
        row_rejected: (N,) bool, dropped because the decoded row and column are inconsistent
            (see the module docstring).
        grazing: (N,) bool, dropped because camera and projector rays (or the column plane)
            meet too obliquely to fix the depth.
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
    """Points from camera rays and decoded projector coordinates (see the module docstring).

    Args:
        rays: (N, 3) camera-frame ray directions through the pixels (any length).
        column: (N,) decoded projector columns (pixels, sub-pixel allowed).
        calib: rig calibration.
        row: (N,) decoded projector rows, or None for column-only codings.
        row_tolerance_px: largest projector reprojection error (px) of a point from both codes.
        min_ray_angle_deg: smallest angle between the camera ray and the projector ray (both
            codes) or the column plane (columns only), degrees.
        iterations: fixed-point iterations for projector distortion without rows.
    """
    if row is None:
        return _from_columns(rays, column, calib, row_tolerance_px, min_ray_angle_deg, iterations)
    return _from_both(rays, column, row, calib, row_tolerance_px, min_ray_angle_deg)


def _from_both(rays: np.ndarray, column: np.ndarray, row: np.ndarray, calib: RigCalibration,
               tolerance_px: float, min_angle_deg: float) -> Triangulation:
    proj = calib.projector
    ideal = proj.undistort(np.column_stack([np.asarray(column, np.float64),
                                            np.asarray(row, np.float64)]))
    xp, yp = ideal[:, 0], ideal[:, 1]
    R, T = calib.R, calib.T
    x, y, z = rays[:, 0], rays[:, 1], rays[:, 2]
    # the rays in the projector's axes, component by component (cheaper than an (N,3) matmul)
    r0 = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z
    r1 = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z
    r2 = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z
    a_col = r0 - xp * r2
    b_col = T[0] - xp * T[2]
    a_row = r1 - yp * r2
    b_row = T[1] - yp * T[2]
    w_col, w_row = proj.K[0, 0] ** 2, proj.K[1, 1] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -(w_col * a_col * b_col + w_row * a_row * b_row) / (
            w_col * a_col * a_col + w_row * a_row * a_row)
        zp = s * r2 + T[2]  # depth in front of the projector
        # reprojection error (projector px) of the point against the decoded column and row
        err2 = (w_col * (a_col * s + b_col) ** 2 + w_row * (a_row * s + b_row) ** 2) / (zp * zp)
    # angle between the camera ray and the projector ray (xp, yp, 1): in the projector's axes
    # their cross product is (a_row, −a_col, r0·yp − r1·xp)
    c2 = r0 * yp - r1 * xp
    sin2 = (a_col * a_col + a_row * a_row + c2 * c2) / (
        (r0 * r0 + r1 * r1 + r2 * r2) * (1.0 + xp * xp + yp * yp))
    grazing = sin2 < np.sin(np.deg2rad(min_angle_deg)) ** 2
    ok = np.isfinite(s) & (s > 0) & (zp > 0) & ~grazing
    row_rejected = ok & ~(err2 <= tolerance_px ** 2)
    ok &= ~row_rejected
    pts = rays * np.where(ok, s, np.nan)[:, None]
    return Triangulation(pts, ok, row_rejected, grazing)


def _from_columns(rays: np.ndarray, column: np.ndarray, calib: RigCalibration,
                  tolerance_px: float, min_angle_deg: float, iterations: int) -> Triangulation:
    del tolerance_px  # nothing to check the column against without rows
    proj = calib.projector
    n = len(column)
    col = np.asarray(column, np.float64)
    guess_row = np.full(n, proj.K[1, 2])
    pts = np.full((n, 3), np.nan)
    sin_angle = np.zeros(n)
    for _ in range(iterations):
        ideal = proj.undistort(np.column_stack([col, guess_row]))
        normal_p = np.column_stack([np.ones(n), np.zeros(n), -ideal[:, 0]])  # plane in proj frame
        normal_c = normal_p @ calib.R  # (R^T n_p) as rows
        offset = normal_p @ calib.T
        denom = np.einsum("ij,ij->i", normal_c, rays)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = -offset / denom
        pts = rays * s[:, None]
        sin_angle = np.abs(denom) / (np.linalg.norm(normal_c, axis=1) * np.linalg.norm(rays, axis=1))
        predicted = proj.project(np.where(np.isfinite(pts), pts, 0.0) @ calib.R.T + calib.T)
        guess_row = predicted[:, 1]
    grazing = sin_angle < np.sin(np.deg2rad(min_angle_deg))
    ok = np.isfinite(pts).all(axis=1) & (pts[:, 2] > 0) & ~grazing
    pts[~ok] = np.nan
    return Triangulation(pts, ok, np.zeros(n, bool), grazing)
