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

Speed (docs/performance.md): the point solves are compiled loops (numba) over the pixels, split
across the cores (:mod:`dotshell.runtime.parallel`); camera rays come from a grid computed once per
camera (a lookup table of every pixel's undistorted ray), the projector's distortion is undone
per point by OpenCV's fixed-point iteration run to convergence (measured faster than a lookup
table of the projector's pixels, whose scattered reads miss the cache), and
:func:`triangulate_image` triangulates a decoded image in place, without gathering its pixels,
optionally moving the points into another frame (the sample's) on the way. With both codes it
works row by row: a row's decoded pixels are gathered into short buffers, all of them take the
undistortion steps together (four, then one at a time while one of them still moves) and the
least-squares solve in loops without branches, which the compiler vectorizes across pixels (2x
faster than one pixel at a time), and pixels whose last step still moved iterate on alone to
convergence.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numba
import numpy as np

from dotshell.runtime import hugepages, numba_cache
from dotshell.geometry.calibration import RigCalibration
from dotshell.geometry.lens import Lens
from dotshell.runtime.parallel import balanced_bands, split, split_bands

numba_cache.install()  # cache files safe for processes compiling at once


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
def _ideal_grid(key: tuple) -> np.ndarray:
    K, dist, w, h = key
    lens = Lens(np.array(K).reshape(3, 3), np.array(dist), w, h)
    ys, xs = np.mgrid[0:h, 0:w]
    px = np.column_stack([xs.ravel(), ys.ravel()]).astype(np.float64)
    return np.ascontiguousarray(lens.undistort(px).reshape(h, w, 2))


def lens_key(lens: Lens) -> tuple:
    """What identifies a lens's pixel grid (intrinsics, distortion, size): a cache key."""
    return (tuple(lens.K.ravel()), tuple(lens.dist), lens.width, lens.height)


def camera_ideal_grid(lens: Lens) -> np.ndarray:
    """(H, W, 2) ideal normalized coordinates (x_n, y_n) of every camera pixel centre: the
    camera rays' directions without their third component, which is 1 (what the image solves
    read: a third less memory traffic than :func:`camera_ray_grid`)."""
    return _ideal_grid(lens_key(lens))


def camera_ray_grid(lens: Lens) -> np.ndarray:
    """(H, W, 3) un-normalized ray directions (x_n, y_n, 1) for every camera pixel centre."""
    xy = camera_ideal_grid(lens)
    return np.concatenate([xy, np.ones((*xy.shape[:2], 1))], axis=2)


@dataclass
class _Rig:
    """The calibration as the compiled solves take it."""

    R: np.ndarray
    T: np.ndarray
    K: np.ndarray
    dist: np.ndarray
    tolerance2: float
    sin2_min: float

    @classmethod
    def of(cls, calib: RigCalibration, tolerance_px: float, min_angle_deg: float) -> _Rig:
        return cls(np.ascontiguousarray(calib.R, np.float64),
                   np.ascontiguousarray(calib.T, np.float64).ravel(),
                   calib.projector.K, _twelve_terms(calib.projector.dist),
                   float(tolerance_px) ** 2, float(np.sin(np.deg2rad(min_angle_deg))) ** 2)

    def args(self) -> tuple:
        return (self.R, self.T, self.K, self.dist, self.tolerance2, self.sin2_min)


def _twelve_terms(dist: np.ndarray) -> np.ndarray:
    """Distortion as the compiled solves take it: OpenCV's first 12 terms (k1, k2, p1, p2, k3,
    k4, k5, k6, s1, s2, s3, s4), zeros for those a 5-term lens does not use."""
    out = np.zeros(12)
    out[: len(dist)] = dist
    return out


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
    rays = np.ascontiguousarray(rays, np.float64).reshape(-1, 3)
    n = len(rays)
    column = np.ascontiguousarray(column, np.float64).ravel()
    rows = np.zeros(0) if row is None else np.ascontiguousarray(row, np.float64).ravel()
    pts = np.empty((n, 3))
    flags = np.empty(n, np.uint8)
    split(_solve_rays, n, rays, column, rows, row is not None, iterations,
          *_Rig.of(calib, row_tolerance_px, min_ray_angle_deg).args(), pts, flags)
    return Triangulation(pts, flags == KEPT, flags == ROW_REJECTED, flags == GRAZING)


@dataclass
class ImagePoints:
    """Points of the decoded pixels of one camera image (:func:`triangulate_image`).

    Attributes:
        pixels: (N, 2) int32 camera pixels (x, y) of the points, in raster order.
        points: (N, 3) float64 points in the requested frame (mm).
        depth: (N,) camera-frame depth z (mm).
        counts: ``triangulated``, ``row_rejected``, ``grazing`` over the decoded pixels.
    """

    pixels: np.ndarray
    points: np.ndarray
    depth: np.ndarray
    counts: dict[str, int]


@dataclass
class ImageSolve:
    """Every decoded pixel of one camera image solved (:func:`solve_image`), kept or not.

    Attributes:
        pixels: (N, 2) int32 camera pixels (x, y), in raster order.
        points: (N, 3) float64 points in the requested frame (mm), NaN where not kept.
        depth: (N,) camera-frame depth z (mm), NaN where not kept.
        kept: (N,) bool, the points that passed the solve's checks.
        counts: ``triangulated``, ``row_rejected``, ``grazing`` over the decoded pixels.
        depth_image: (H, W) float32 camera depths of the kept points (mm), 0 elsewhere, if
            asked for (the speckle test's input, written by the solve as it goes).
        skipped: decoded pixels outside the columns the solve was given, not solved.
    """

    pixels: np.ndarray
    points: np.ndarray
    depth: np.ndarray
    kept: np.ndarray
    counts: dict[str, int]
    depth_image: np.ndarray | None = None
    skipped: int = 0


def triangulate_image(valid: np.ndarray, column: np.ndarray, row: np.ndarray | None,
                      calib: RigCalibration, row_tolerance_px: float = 1.5,
                      min_ray_angle_deg: float = 5.0, to_frame: np.ndarray | None = None,
                      iterations: int = 3) -> ImagePoints:
    """Triangulate every ``valid`` pixel of decoded (H, W) column (and row) maps, as
    :func:`triangulate` does, and keep the points that pass its checks.

    ``to_frame``: optional (3, 4) affine map [A | b] taking camera-frame points (row vectors)
    to the output frame, ``p_out = A @ p + b``; default the camera frame."""
    sol = solve_image(valid, column, row, calib, row_tolerance_px, min_ray_angle_deg, to_frame,
                      iterations)
    pixels, points, depth = select(sol.kept, sol.pixels, sol.points, sol.depth)
    return ImagePoints(pixels, points, depth, sol.counts)


def solve_image(valid: np.ndarray, column: np.ndarray, row: np.ndarray | None,
                calib: RigCalibration, row_tolerance_px: float = 1.5,
                min_ray_angle_deg: float = 5.0, to_frame: np.ndarray | None = None,
                iterations: int = 3, depth_image: bool = False,
                columns: np.ndarray | None = None) -> ImageSolve:
    """:func:`triangulate_image` without the selection: every ``valid`` pixel's solve, for a
    caller that filters the points further and selects once (``depth_image``: also the
    image of the kept points' depths, :class:`ImageSolve`; ``columns``: (H, 2) int64, per
    row the columns ``[x0, x1)`` to solve, the others' pixels only counted as ``skipped``,
    e.g. :func:`dotshell.geometry.roi_rays.roi_columns`)."""
    h, w = valid.shape
    rays = camera_ideal_grid(calib.camera)
    if rays.shape[:2] != (h, w):
        raise ValueError(f"decoded maps are {w}x{h} px but the calibration's camera is "
                         f"{calib.camera.width}x{calib.camera.height} px")
    affine = np.eye(3, 4) if to_frame is None else np.ascontiguousarray(to_frame, np.float64)
    rows = np.zeros((0, 0), np.float32) if row is None else row
    if columns is None:
        columns = np.zeros((h, 2), np.int64)
        columns[:, 1] = w
    per_row = np.empty(h, np.int64)
    outside = np.empty(h, np.int64)
    split(_count_rows, h, valid, columns, per_row, outside)
    start = np.concatenate([[0], np.cumsum(per_row)])
    n = int(start[-1])
    pts = hugepages.empty((n, 3), np.float64)
    depth = hugepages.empty(n, np.float64)
    pixels = hugepages.empty((n, 2), np.int32)
    kept = np.empty(n, bool)
    image = hugepages.empty((h, w) if depth_image else (0, 0), np.float32)
    # rows cut by their decoded pixels (a row's solve costs ~1 pixel's per 50 px it scans)
    bounds = balanced_bands(per_row + (columns[:, 1] - columns[:, 0]) / 50.0,
                            per_worker=SOLVE_BANDS_PER_WORKER)
    counts = np.zeros((len(bounds) - 1, 4), np.int64)  # per band, by flag
    split_bands(_solve_image, bounds, valid, columns, column, rows, row is not None, iterations,
                rays, start, affine, *_Rig.of(calib, row_tolerance_px, min_ray_angle_deg).args(),
                pts, depth, pixels, kept, image, counts)
    total = counts.sum(axis=0)
    return ImageSolve(pixels, pts, depth, kept,
                      {"triangulated": int(total[KEPT]), "row_rejected": int(total[ROW_REJECTED]),
                       "grazing": int(total[GRAZING])}, image if depth_image else None,
                      int(outside.sum()))


def select(mask: np.ndarray, *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """``a[mask]`` for each array, computed in place (the arrays' first ``mask.sum()`` rows
    are overwritten; the results are views of them): one compiled pass instead of a boolean
    index per array (50 ms for a view's points in numpy on a busy machine). Serial: the copy
    is bound by memory, and copying into new arrays on two cores was no faster (measured)."""
    n = 0
    for a in arrays:
        n = _select_in_place(mask, a.reshape(len(a), int(np.prod(a.shape[1:]))))
    return tuple(a[:n] for a in arrays) if arrays else ()


# ---- compiled solves ------------------------------------------------------------------------

KEPT, DROPPED, ROW_REJECTED, GRAZING = 0, 1, 2, 3
#: bands of rows per core in :func:`solve_image`, taken by the cores one at a time: the core
#: that finishes its last band first waits for the other, ~half a band on average (with 2 a
#: core, ~1.7 ms of a full view's ~13.5 ms of CPU); a band costs a few short buffers
SOLVE_BANDS_PER_WORKER = 6
_OPTS: dict = dict(nogil=True, cache=True, error_model="numpy")  # njit's keywords differ in type
#: per-point helpers are inlined: a compiled call passing arrays pays reference counting
_INNER: dict = dict(_OPTS, inline="always")
MAX_UNDISTORT_STEPS = 50
#: undistortion steps every pixel of a row takes together (:func:`_ideal_batch`), the first
#: :data:`FIRST_UNDISTORT_STEPS` without looking, the rest while one of them still moves; 4-6
#: reach convergence for the rigs measured, the rest continue alone
BATCH_UNDISTORT_STEPS = 8
FIRST_UNDISTORT_STEPS = 4


@numba.njit(**_INNER)
def _ideal(K, dist, u, v):
    """Ideal normalized coordinates of distorted pixel (u, v): the Brown–Conrady model
    inverted by fixed-point iteration, as ``cv2.undistortPoints`` does, to convergence
    (|step| < 1e-15; each step divides the error by ~1 / (3 |k1| r²), 100 or more here)."""
    return _ideal_from(K, dist, u, v, (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1])


@numba.njit(**_INNER)
def _ideal_from(K, dist, u, v, x, y):
    """:func:`_ideal` iterated from the guess (x, y)."""
    x0 = (u - K[0, 2]) / K[0, 0]
    y0 = (v - K[1, 2]) / K[1, 1]
    for _ in range(MAX_UNDISTORT_STEPS):
        nx, ny = _undistort_step(dist, x0, y0, x, y)
        if abs(nx - x) < 1e-15 and abs(ny - y) < 1e-15:
            return nx, ny
        x, y = nx, ny
    return x, y


@numba.njit(**_INNER)
def _undistort_step(d, x0, y0, x, y):
    """One fixed-point step towards the ideal point (x, y) whose distorted image is (x0, y0)
    (normalized coordinates); ``d``: the 12 terms of :func:`_twelve_terms`."""
    r2 = x * x + y * y
    icdist = (1.0 + ((d[7] * r2 + d[6]) * r2 + d[5]) * r2) / (
        1.0 + ((d[4] * r2 + d[1]) * r2 + d[0]) * r2)
    dx = 2.0 * d[2] * x * y + d[3] * (r2 + 2.0 * x * x) + (d[8] + d[9] * r2) * r2
    dy = d[2] * (r2 + 2.0 * y * y) + 2.0 * d[3] * x * y + (d[10] + d[11] * r2) * r2
    return (x0 - dx) * icdist, (y0 - dy) * icdist


@numba.njit(**_INNER)
def _ideal_batch(K, dist, u, v, n, xs, ys, last, x0s, y0s):
    """:func:`_ideal` of the first ``n`` pixels (u, v): :data:`FIRST_UNDISTORT_STEPS` steps
    for all of them in a loop without branches that the compiler vectorizes across pixels,
    then one step at a time for all while one of them still moves (at most
    :data:`BATCH_UNDISTORT_STEPS` in all), then iterated on to convergence where the last step
    still moved (``last``: scratch; ``x0s``, ``y0s``: scratch, each pixel's distorted
    normalized coordinates, divided out once rather than at every later step)."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    for j in range(n):
        x0 = (u[j] - cx) / fx
        y0 = (v[j] - cy) / fy
        x, y = x0, y0
        step = 0.0
        for _ in range(FIRST_UNDISTORT_STEPS):
            nx, ny = _undistort_step(dist, x0, y0, x, y)
            step = max(abs(nx - x), abs(ny - y))
            x, y = nx, ny
        xs[j] = x
        ys[j] = y
        x0s[j] = x0
        y0s[j] = y0
        last[j] = step
    for _ in range(BATCH_UNDISTORT_STEPS - FIRST_UNDISTORT_STEPS):
        moving = 0
        for j in range(n):
            moving += not last[j] < 1e-15
        if moving == 0:
            break
        for j in range(n):
            nx, ny = _undistort_step(dist, x0s[j], y0s[j], xs[j], ys[j])
            last[j] = max(abs(nx - xs[j]), abs(ny - ys[j]))
            xs[j] = nx
            ys[j] = ny
    for j in range(n):
        if not last[j] < 1e-15:
            xs[j], ys[j] = _ideal_from(K, dist, u[j], v[j], xs[j], ys[j])


@numba.njit(**_INNER)
def _both(x, y, z, u, v, R, T, K, dist, tolerance2, sin2_min):
    """(s, flag): the point is ``s`` × ray from column u and row v (module docstring)."""
    xp, yp = _ideal(K, dist, u, v)
    return _both_ideal(x, y, z, xp, yp, _pose(R, T, K), tolerance2, sin2_min)


@numba.njit(**_INNER)
def _pose(R, T, K):
    """R (row by row), T and the squared projector focal lengths as one tuple of scalars, so
    that loops over points keep them in registers (arrays might alias the outputs)."""
    return (R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2, 0], R[2, 1], R[2, 2],
            T[0], T[1], T[2], K[0, 0] ** 2, K[1, 1] ** 2)


@numba.njit(**_INNER)
def _both_ideal(x, y, z, xp, yp, pose, tolerance2, sin2_min):
    """:func:`_both` from the projector's ideal normalized coordinates (xp, yp) and
    :func:`_pose`, written without branches (the flag by selection) so that loops over
    points vectorize."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22, t0, t1, t2, w_col, w_row = pose
    r0 = r00 * x + r01 * y + r02 * z
    r1 = r10 * x + r11 * y + r12 * z
    r2 = r20 * x + r21 * y + r22 * z
    a_col = r0 - xp * r2
    b_col = t0 - xp * t2
    a_row = r1 - yp * r2
    b_row = t1 - yp * t2
    s = -(w_col * a_col * b_col + w_row * a_row * b_row) / (
        w_col * a_col * a_col + w_row * a_row * a_row)
    zp = s * r2 + t2
    e_col = a_col * s + b_col
    e_row = a_row * s + b_row
    err2 = (w_col * e_col * e_col + w_row * e_row * e_row) / (zp * zp)
    c2 = r0 * yp - r1 * xp
    sin2 = (a_col * a_col + a_row * a_row + c2 * c2) / (
        (r0 * r0 + r1 * r1 + r2 * r2) * (1.0 + xp * xp + yp * yp))
    flag = KEPT if err2 <= tolerance2 else ROW_REJECTED
    flag = flag if np.isfinite(s) and s > 0 and zp > 0 else DROPPED
    return s, GRAZING if sin2 < sin2_min else flag


@numba.njit(**_INNER)
def _project_y(K, dist, px, py, pz):
    """Distorted projector pixel row of a projector-frame point (OpenCV's model)."""
    x = px / pz
    y = py / pz
    r2 = x * x + y * y
    radial = (1.0 + r2 * (dist[0] + r2 * (dist[1] + r2 * dist[4]))) / (
        1.0 + r2 * (dist[5] + r2 * (dist[6] + r2 * dist[7])))
    yd = (y * radial + dist[2] * (r2 + 2.0 * y * y) + 2.0 * dist[3] * x * y
          + (dist[10] + dist[11] * r2) * r2)
    return K[1, 1] * yd + K[1, 2]


@numba.njit(**_INNER)
def _columns(x, y, z, u, iterations, R, T, K, dist, sin2_min):
    """(s, flag) from column u only: the ray meets the column plane, whose bend by the
    projector's distortion follows the predicted row (fixed-point iterations)."""
    guess = K[1, 2]
    s = np.nan
    sin2 = 0.0
    for _ in range(iterations):
        xi, _yi = _ideal(K, dist, u, guess)
        # plane normal (1, 0, -xi) in the projector frame, R^T n in the camera frame
        n0 = R[0, 0] - xi * R[2, 0]
        n1 = R[0, 1] - xi * R[2, 1]
        n2 = R[0, 2] - xi * R[2, 2]
        offset = T[0] - xi * T[2]
        denom = n0 * x + n1 * y + n2 * z
        s = -offset / denom
        sin2 = denom * denom / ((n0 * n0 + n1 * n1 + n2 * n2) * (x * x + y * y + z * z))
        px, py, pz = s * x, s * y, s * z
        if not (np.isfinite(px) and np.isfinite(py) and np.isfinite(pz)):
            px, py, pz = (px if np.isfinite(px) else 0.0, py if np.isfinite(py) else 0.0,
                          pz if np.isfinite(pz) else 0.0)
        qx = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + T[0]
        qy = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + T[1]
        qz = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + T[2]
        guess = _project_y(K, dist, qx, qy, qz)
    if sin2 < sin2_min:
        return s, GRAZING
    if not (np.isfinite(s * x) and np.isfinite(s * y) and np.isfinite(s * z) and s * z > 0):
        return s, DROPPED
    return s, KEPT


@numba.njit(**_INNER)
def _solve(x, y, z, u, v, has_rows, iterations, R, T, K, dist, tolerance2, sin2_min):
    if has_rows:
        return _both(x, y, z, u, v, R, T, K, dist, tolerance2, sin2_min)
    return _columns(x, y, z, u, iterations, R, T, K, dist, sin2_min)


@numba.njit(**_OPTS)
def _solve_rays(rays, column, row, has_rows, iterations, R, T, K, dist, tolerance2,
                sin2_min, pts, flags, start, stop):
    for i in range(start, stop):
        x, y, z = rays[i, 0], rays[i, 1], rays[i, 2]
        s, f = _solve(x, y, z, column[i], row[i] if has_rows else 0.0, has_rows, iterations,
                      R, T, K, dist, tolerance2, sin2_min)
        flags[i] = f
        if f != KEPT:
            s = np.nan
        pts[i, 0], pts[i, 1], pts[i, 2] = s * x, s * y, s * z


@numba.njit(**_OPTS)
def _select_in_place(mask, rows):
    n = 0
    for i in range(mask.shape[0]):
        if mask[i]:
            if n != i:
                for k in range(rows.shape[1]):
                    rows[n, k] = rows[i, k]
            n += 1
    return n


@numba.njit(**_OPTS)
def _count_rows(valid, columns, out, outside, start, stop):
    """Rows ``start`` to ``stop``: the ``valid`` pixels in each row's ``columns`` range
    (``out``) and outside it (``outside``). The range is counted as a slice from its start
    (vectorized: a loop from ``columns[y, 0]`` was not, 0.47 against 0.12 ms a full view)."""
    for y in range(start, stop):
        row = valid[y]
        c = 0
        for x in range(row.shape[0]):
            c += row[x]
        inside_range = row[columns[y, 0]:columns[y, 1]]
        inside = 0
        for x in range(inside_range.shape[0]):
            inside += inside_range[x]
        out[y] = inside
        outside[y] = c - inside


@numba.njit(**_OPTS)
def _solve_image(valid, columns, column, row, has_rows, iterations, rays, start, affine, R, T,
                 K, dist, tolerance2, sin2_min, pts, depth, pixels, kept, image, counts, band,
                 start_row, stop_row):
    """Rows ``start_row`` to ``stop_row``, each in its ``columns`` range ``[x0, x1)``,
    solved into the outputs from ``start[row]`` on;
    ``counts[band]``: how many got each flag (:data:`KEPT` …); ``image``: the kept points'
    depths in these rows, 0 elsewhere (unless it is empty)."""
    if image.shape[0] > 0:
        image[start_row:stop_row] = 0
    if has_rows:
        _solve_rows_both(valid, columns, column, row, rays, start, affine, R, T, K, dist,
                         tolerance2, sin2_min, pts, depth, pixels, kept, image, counts[band],
                         start_row, stop_row)
        return
    for yy in range(start_row, stop_row):
        i = start[yy]
        for xx in range(columns[yy, 0], columns[yy, 1]):
            if not valid[yy, xx]:
                continue
            x, y, z = rays[yy, xx, 0], rays[yy, xx, 1], 1.0
            s, f = _columns(x, y, z, np.float64(column[yy, xx]), iterations, R, T, K, dist,
                            sin2_min)
            _store(i, xx, yy, x, y, z, s, f, _affine(affine), pts, depth, pixels, kept)
            counts[band, f] += 1
            if f == KEPT and image.shape[0] > 0:
                image[yy, xx] = depth[i]
            i += 1


@numba.njit(**_INNER)
def _affine(affine):
    """The (3, 4) affine map as a tuple of scalars (see :func:`_pose`)."""
    return (affine[0, 0], affine[0, 1], affine[0, 2], affine[0, 3],
            affine[1, 0], affine[1, 1], affine[1, 2], affine[1, 3],
            affine[2, 0], affine[2, 1], affine[2, 2], affine[2, 3])


@numba.njit(**_INNER)
def _store(i, xx, yy, x, y, z, s, f, aff, pts, depth, pixels, kept):
    """Output ``i``: the point ``s`` × ray (x, y, z) in the frame of ``aff``
    (:func:`_affine`; NaN unless kept), its camera depth, pixel and whether flag ``f`` kept
    it."""
    a00, a01, a02, a03, a10, a11, a12, a13, a20, a21, a22, a23 = aff
    s = s if f == KEPT else np.nan
    px, py, pz = s * x, s * y, s * z
    pts[i, 0] = a00 * px + a01 * py + a02 * pz + a03
    pts[i, 1] = a10 * px + a11 * py + a12 * pz + a13
    pts[i, 2] = a20 * px + a21 * py + a22 * pz + a23
    depth[i] = pz
    pixels[i, 0] = xx
    pixels[i, 1] = yy
    kept[i] = f == KEPT


@numba.njit(**_INNER)
def _solve_rows_both(valid, columns, column, row, rays, start, affine, R, T, K, dist,
                     tolerance2, sin2_min, pts, depth, pixels, kept, image, counts, start_row,
                     stop_row):
    """Both codes, row by row: the row's decoded pixels in its ``columns`` range are gathered
    into short buffers and
    solved in loops without branches (vectorized across pixels); ``counts`` (4,): how many
    got each flag."""
    W = valid.shape[1]
    u, v, xs, ys, last = np.empty(W), np.empty(W), np.empty(W), np.empty(W), np.empty(W)
    rx, ry, scale = np.empty(W), np.empty(W), np.empty(W)
    x0s, y0s = np.empty(W), np.empty(W)
    flag = np.empty(W, np.int64)
    at = np.empty(W, np.int64)
    pose = _pose(R, T, K)
    aff = _affine(affine)
    for yy in range(start_row, stop_row):
        n = 0
        for xx in range(columns[yy, 0], columns[yy, 1]):
            if valid[yy, xx]:
                at[n] = xx
                u[n] = column[yy, xx]
                v[n] = row[yy, xx]
                rx[n], ry[n] = rays[yy, xx, 0], rays[yy, xx, 1]
                n += 1
        _ideal_batch(K, dist, u, v, n, xs, ys, last, x0s, y0s)
        i0 = start[yy]
        n_kept = n_row = n_grazing = 0
        # the solves alone in one loop (it vectorizes: ~2x faster than with the stores in it)
        for j in range(n):
            s, f = _both_ideal(rx[j], ry[j], 1.0, xs[j], ys[j], pose, tolerance2, sin2_min)
            scale[j] = s
            flag[j] = f
            n_kept += f == KEPT
            n_row += f == ROW_REJECTED
            n_grazing += f == GRAZING
        for j in range(n):
            _store(i0 + j, at[j], yy, rx[j], ry[j], 1.0, scale[j], flag[j], aff, pts, depth,
                   pixels, kept)
        counts[KEPT] += n_kept
        counts[ROW_REJECTED] += n_row
        counts[GRAZING] += n_grazing
        counts[DROPPED] += n - n_kept - n_row - n_grazing
        if image.shape[0] > 0:
            for j in range(n):
                if kept[i0 + j]:
                    image[yy, at[j]] = depth[i0 + j]
