"""Which camera pixels can see the region of interest: the columns of each image row whose
camera rays meet the ROI cylinder (``[processing.roi]``: radius about the turntable axis, a
height range above the plate), so that a view's solve can skip the others — wherever such a
pixel would triangulate, its point lies outside the region and is lost.

The point of a pixel lies on its camera ray (:mod:`dotshell.geometry.triangulate`: ``s`` × the
undistorted ray, ``s`` > 0), and the cylinder is the sample frame's, about the turntable axis,
so whether a ray meets it is the same at every stage angle: it depends on the camera's lens,
the axis and the ROI only, and is computed once for them (cached). The test is conservative:
the cylinder is widened by :data:`MARGIN_MM` each way (far above the rounding of the sample
frame's map, ~1e-10 mm), and each row's range is widened by the speckle test's reach
(:data:`REACH_PX` pixels each way, and from the rows as far above and below), so a point the
region keeps sees exactly the neighbourhood it saw before in the depth image
(:func:`dotshell.pipeline.reconstruct.keep_points`): the points kept are the same, bit for bit.
"""

from __future__ import annotations

import numba
import numpy as np

from dotshell.geometry.calibration import RigCalibration
from dotshell.geometry.triangulate import camera_ideal_grid, lens_key
from dotshell.runtime import numba_cache
from dotshell.runtime.parallel import split

numba_cache.install()  # cache files safe for processes compiling at once

#: the cylinder is widened by this much, radially and at both ends (mm)
MARGIN_MM = 0.01
#: pixels each way a row's range is widened by (the speckle test's 5×5 neighbourhood)
REACH_PX = 2


def roi_columns(calib: RigCalibration, radius_mm: float, z_min_mm: float, z_max_mm: float
                ) -> np.ndarray:
    """(H, 2) int64: per camera row the columns ``[x0, x1)`` to solve — those whose rays meet
    the ROI cylinder, widened (module docstring); ``x0 = x1 = 0`` where none does; every
    column where the ROI is not finite. Read-only, computed once per lens, axis and ROI
    (~5 ms of CPU a 1280×1024 camera)."""
    key = (lens_key(calib.camera), tuple(calib.axis_point), tuple(calib.axis_direction),
           float(radius_mm), float(z_min_mm), float(z_max_mm))
    columns = _CACHE.get(key)
    if columns is None:
        columns = _columns(calib, *key[3:])
        columns.flags.writeable = False
        while len(_CACHE) >= _CACHED:
            _CACHE.pop(next(iter(_CACHE)))
        _CACHE[key] = columns
    return columns


#: :func:`roi_columns` of the last few lenses, axes and ROIs
_CACHE: dict[tuple, np.ndarray] = {}
_CACHED = 4


def _columns(calib: RigCalibration, radius: float, z_min: float, z_max: float) -> np.ndarray:
    h, w = calib.camera.height, calib.camera.width
    out = np.zeros((h, 2), np.int64)
    if not all(np.isfinite((radius, z_min, z_max))):
        out[:, 1] = w
        return out
    basis = np.ascontiguousarray(calib.stage_basis(), np.float64)
    origin = -basis @ np.asarray(calib.axis_point, np.float64)  # the camera centre, stage frame
    first, last = np.empty(h, np.int64), np.empty(h, np.int64)
    split(_row_hits, h, camera_ideal_grid(calib.camera), basis, origin, radius + MARGIN_MM,
          z_min - MARGIN_MM, z_max + MARGIN_MM, first, last)
    x0, x1 = first.copy(), last.copy()
    for dy in range(1, REACH_PX + 1):  # the rows REACH_PX above and below
        x0[dy:] = np.minimum(x0[dy:], first[:-dy])
        x0[:-dy] = np.minimum(x0[:-dy], first[dy:])
        x1[dy:] = np.maximum(x1[dy:], last[:-dy])
        x1[:-dy] = np.maximum(x1[:-dy], last[dy:])
    seen = x1 >= x0
    out[:, 0] = np.where(seen, np.maximum(x0 - REACH_PX, 0), 0)
    out[:, 1] = np.where(seen, np.minimum(x1 + REACH_PX + 1, w), 0)
    return out


@numba.njit(nogil=True, cache=True)
def _row_hits(ideal, basis, origin, radius, z_min, z_max, first, last, start, stop):
    """Rows ``start`` to ``stop``: the first and last column whose ray meets the cylinder
    (:func:`ray_meets_cylinder`; the width and −1 where none does)."""
    w = ideal.shape[1]
    for y in range(start, stop):
        lo, hi = w, -1
        for x in range(w):
            if ray_meets_cylinder(ideal[y, x, 0], ideal[y, x, 1], basis, origin, radius,
                                  z_min, z_max):
                lo = min(lo, x)
                hi = x
        first[y] = lo
        last[y] = hi


@numba.njit(nogil=True, cache=True)
def ray_meets_cylinder(xn: float, yn: float, basis: np.ndarray, origin: np.ndarray,
                       radius: float, z_min: float, z_max: float) -> bool:
    """The camera ray ``origin + s · basis @ (xn, yn, 1)``, ``s`` > 0 (stage frame, mm; ``basis``:
    the stage frame's axes as rows, camera frame), meets the cylinder ``x² + y² ≤ radius²``,
    ``z_min ≤ z ≤ z_max``."""
    dx = basis[0, 0] * xn + basis[0, 1] * yn + basis[0, 2]
    dy = basis[1, 0] * xn + basis[1, 1] * yn + basis[1, 2]
    dz = basis[2, 0] * xn + basis[2, 1] * yn + basis[2, 2]
    ox, oy, oz = origin[0], origin[1], origin[2]
    a = dx * dx + dy * dy
    b = 2.0 * (ox * dx + oy * dy)
    c = ox * ox + oy * oy - radius * radius
    if a > 0:
        disc = b * b - 4.0 * a * c
        if disc < 0:
            return False
        root = np.sqrt(disc)
        s_in, s_out = (-b - root) / (2.0 * a), (-b + root) / (2.0 * a)
    elif c > 0:
        return False
    else:
        s_in, s_out = -np.inf, np.inf
    if dz != 0:
        t1, t2 = (z_min - oz) / dz, (z_max - oz) / dz
        z_in, z_out = min(t1, t2), max(t1, t2)
    elif z_min <= oz <= z_max:
        z_in, z_out = -np.inf, np.inf
    else:
        return False
    enter = max(s_in, z_in, 0.0)
    leave = min(s_out, z_out)
    return leave >= enter and leave > 0
