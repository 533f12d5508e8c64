"""Per-view reconstruction: decode frames → triangulate → sample frame → region of interest."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numba
import numpy as np

from dotshell.runtime import hugepages, numba_cache
from dotshell.coding import Correspondence, PatternCoding
from dotshell.errors import CalibrationError, ReconstructionError
from dotshell.geometry.calibration import RigCalibration
from dotshell.geometry.roi_rays import roi_columns
from dotshell.geometry.triangulate import ImageSolve, select, solve_image
from dotshell.pipeline.decode_quality import WRONG_CODES, view_quality
from dotshell.runtime.parallel import bands, split, split_bands

numba_cache.install()  # cache files safe for processes compiling at once

#: bands of points per core in the keep pass and its gather (taken by the cores one at a time;
#: the core that finishes first waits ~half a band for the other)
KEEP_BANDS_PER_WORKER = 6


@dataclass
class ViewCloud:
    """One view's points in the sample frame (mm) with the camera pixels (x, y) they came from.
    ``pixels`` and ``correspondence`` may be dropped (None) once no later step needs them."""

    view: int
    angle_deg: float
    points: np.ndarray
    pixels: np.ndarray | None
    correspondence: Correspondence | None
    stats: dict[str, Any] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    #: :func:`~dotshell.pipeline.decode_quality.view_quality`: decoded share, reversals
    quality: dict[str, Any] = field(default_factory=dict)


def in_roi(points: np.ndarray, roi: Mapping[str, float]) -> np.ndarray:
    """Mask of sample-frame points (N, 3) inside the cylindrical region of interest."""
    out = np.empty(len(points), bool)
    split(_in_cylinder, len(points), np.ascontiguousarray(points, np.float64),
          float(roi["radius_mm"]), float(roi["z_min_mm"]), float(roi["z_max_mm"]), out)
    return out


def speckle_mask(pixels: np.ndarray, depth_mm: np.ndarray, shape: tuple[int, int],
                 max_jump_mm: float, kept: np.ndarray | None = None) -> np.ndarray:
    """True for points whose depth agrees with the median of their 5×5 camera neighbourhood
    within ``max_jump_mm`` (isolated decoding errors — speckles — fail). Pixels without
    points count as depth 0 (float32 depths, the image border replicated, as OpenCV's
    ``medianBlur`` of the depth image), so a point needs mostly valid neighbours to pass.
    ``kept``: only these points are points (the others are neither in the depth image nor
    tested, and get False).

    Computed per point without sorting: the median m of the 25 values lies within
    [d − j, d + j] exactly when at least 13 values v have ``v − d ≤ j`` and at least 13 have
    ``v − d ≥ −j`` (v − d is monotone in v), which is the same test on the same numbers."""
    pixels = np.ascontiguousarray(pixels)
    depth = np.ascontiguousarray(depth_mm, np.float64)
    kept = np.ones(len(depth), bool) if kept is None else np.ascontiguousarray(kept, bool)
    img = depth_image(pixels, depth, kept, shape)
    out = np.empty(len(depth), bool)
    split(_median_within, len(depth), pixels, depth, kept, img, float(max_jump_mm), out)
    return out


def depth_image(pixels: np.ndarray, depth_mm: np.ndarray, kept: np.ndarray,
                shape: tuple[int, int]) -> np.ndarray:
    """(H, W) float32 image of the ``kept`` points' depths (mm), 0 where there is none."""
    img = hugepages.zeros(shape, np.float32)
    split(_scatter, len(depth_mm), pixels, depth_mm, kept, img)
    return img


def view_points(sol: ImageSolve, shape: tuple[int, int], max_jump_mm: float,
                roi: Mapping[str, float]) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """The kept points of :func:`keep_points` gathered: their camera pixels (N, 2) int32,
    points (N, 3) float64 (mm) and the counts. Each band of the keep pass copies its own
    kept points to where the bands before it end, both cores at once."""
    keep, counts, bounds, per_band = _keep(sol, shape, max_jump_mm, roi)
    ends = np.concatenate([[0], np.cumsum(per_band)])
    pixels = hugepages.empty((int(ends[-1]), 2), np.int32)
    points = hugepages.empty((int(ends[-1]), 3), np.float64)
    split_bands(_gather, bounds, keep, np.ascontiguousarray(sol.pixels),
                np.ascontiguousarray(sol.points, np.float64), ends, pixels, points)
    return pixels, points, counts


def keep_points(sol: ImageSolve, shape: tuple[int, int], max_jump_mm: float,
                roi: Mapping[str, float]) -> tuple[np.ndarray, dict[str, int]]:
    """The points of a view to keep — solved (``sol.kept``), inside the region of interest
    and, if ``max_jump_mm`` > 0, not speckles (:func:`speckle_mask`) — and the counts
    ``outside_roi`` (solved, outside), ``speckle`` (solved, inside, failing the speckle test)
    and ``points`` (kept), in one pass after the depth image.

    The speckle test's medians take the depths of all the solved points, inside the region or
    not; only the points inside are tested, since a point outside is lost either way (the
    same points as testing every one, with a quarter fewer tests on the bench view)."""
    keep, counts, _, _ = _keep(sol, shape, max_jump_mm, roi)
    return keep, counts


def _keep(sol: ImageSolve, shape: tuple[int, int], max_jump_mm: float, roi: Mapping[str, float]
          ) -> tuple[np.ndarray, dict[str, int], list[int], np.ndarray]:
    """:func:`keep_points`, and the bounds of the bands it was cut into with their kept
    points."""
    pixels = np.ascontiguousarray(sol.pixels)
    depth = np.ascontiguousarray(sol.depth, np.float64)
    kept = np.ascontiguousarray(sol.kept, bool)
    test = max_jump_mm > 0
    img = np.zeros((1, 1), np.float32)
    if test:  # the one the solve wrote as it went, if it did
        img = sol.depth_image if sol.depth_image is not None else depth_image(pixels, depth,
                                                                              kept, shape)
    keep = np.empty(len(depth), bool)
    bounds = bands(len(depth), min_chunk=1 << 14, per_worker=KEEP_BANDS_PER_WORKER)
    counts = np.zeros((len(bounds) - 1, 3), np.int64)
    split_bands(_keep_points, bounds, kept, pixels, depth,
                np.ascontiguousarray(sol.points, np.float64), float(roi["radius_mm"]),
                float(roi["z_min_mm"]), float(roi["z_max_mm"]), img, test, float(max_jump_mm),
                keep, counts)
    outside, speckle, n = (int(c) for c in counts.sum(axis=0))
    return keep, {"outside_roi": outside, "speckle": speckle, "points": n}, bounds, counts[:, 2]


@numba.njit(nogil=True, cache=True, inline="always")
def _inside(points, i, radius, z_min, z_max):
    x, y, z = points[i, 0], points[i, 1], points[i, 2]
    return x * x + y * y <= radius * radius and z_min <= z <= z_max


@numba.njit(nogil=True, cache=True)
def _in_cylinder(points, radius, z_min, z_max, out, start, stop):
    for i in range(start, stop):
        out[i] = _inside(points, i, radius, z_min, z_max)


@numba.njit(nogil=True, cache=True)
def _keep_points(kept, pixels, depth, points, radius, z_min, z_max, img, test, max_jump, keep,
                 counts, band, start, stop):
    """Points ``start`` to ``stop`` kept or counted (:func:`keep_points`). The speckle test
    first asks whether the 15 depths of the upper three rows of a point's 5×5 neighbourhood
    all lie within ``max_jump`` (their least and greatest, :func:`_window_extremes`, once per
    image row): then the median does (15 of 25 on each side of it), as the full count
    (:func:`_within`), which the other points take, would decide it."""
    outside = speckle = n = 0
    w = img.shape[1]
    lo, hi = np.empty(w, np.float32), np.empty(w, np.float32)
    col_lo, col_hi = np.empty(w, np.float32), np.empty(w, np.float32)
    row = -1
    for i in range(start, stop):
        keep[i] = False
        if not kept[i]:
            continue
        if not _inside(points, i, radius, z_min, z_max):
            outside += 1
            continue
        if test:
            x, y, d = pixels[i, 0], pixels[i, 1], depth[i]
            if y != row:
                row = y
                _window_extremes(img, y, col_lo, col_hi, lo, hi)
            # float64(v) − d grows with v: the extremes bound all 15 differences
            sure = np.float64(hi[x]) - d <= max_jump and np.float64(lo[x]) - d >= -max_jump
            if not sure and not _within(img, x, y, d, max_jump):
                speckle += 1
                continue
        keep[i] = True
        n += 1
    counts[band, 0] = outside
    counts[band, 1] = speckle
    counts[band, 2] = n


@numba.njit(nogil=True, cache=True, inline="always")
def _window_extremes(img, y, col_lo, col_hi, lo, hi):
    """``lo``/``hi`` (W,): the least and greatest of ``img`` over rows y − 2 … y and columns
    x − 2 … x + 2 (indices clamped to the image, as :func:`_within` reads them), in loops
    without branches (vectorized); ``col_lo``/``col_hi``: scratch (W,)."""
    w = img.shape[1]
    a, b, c = img[max(y - 2, 0)], img[max(y - 1, 0)], img[y]
    for x in range(w):
        col_lo[x] = min(a[x], b[x], c[x])
        col_hi[x] = max(a[x], b[x], c[x])
    for x in range(2, w - 2):
        lo[x] = min(col_lo[x - 2], col_lo[x - 1], col_lo[x], col_lo[x + 1], col_lo[x + 2])
        hi[x] = max(col_hi[x - 2], col_hi[x - 1], col_hi[x], col_hi[x + 1], col_hi[x + 2])
    for x in range(min(2, w)):
        lo[x], hi[x] = _clamped_extremes(col_lo, col_hi, x, w)
    for x in range(max(w - 2, 2), w):
        lo[x], hi[x] = _clamped_extremes(col_lo, col_hi, x, w)


@numba.njit(nogil=True, cache=True, inline="always")
def _clamped_extremes(col_lo, col_hi, x, w):
    """The least of ``col_lo`` and the greatest of ``col_hi`` over columns x − 2 … x + 2
    clamped to [0, w − 1] (near the border)."""
    least, most = col_lo[x], col_hi[x]
    for k in range(max(x - 2, 0), min(x + 2, w - 1) + 1):
        least = min(least, col_lo[k])
        most = max(most, col_hi[k])
    return least, most


@numba.njit(nogil=True, cache=True)
def _gather(keep, pixels, points, ends, out_pixels, out_points, band, start, stop):
    n = ends[band]
    for i in range(start, stop):
        if keep[i]:
            out_pixels[n, 0], out_pixels[n, 1] = pixels[i, 0], pixels[i, 1]
            out_points[n, 0], out_points[n, 1] = points[i, 0], points[i, 1]
            out_points[n, 2] = points[i, 2]
            n += 1


@numba.njit(nogil=True, cache=True)
def _scatter(pixels, depth, kept, img, start, stop):
    for i in range(start, stop):
        if kept[i]:
            img[pixels[i, 1], pixels[i, 0]] = depth[i]


@numba.njit(nogil=True, cache=True)
def _median_within(pixels, depth, kept, img, max_jump, out, start, stop):
    for i in range(start, stop):
        out[i] = kept[i] and _within(img, pixels[i, 0], pixels[i, 1], depth[i], max_jump)


@numba.njit(nogil=True, cache=True, inline="always")
def _within(img, x, y, d, j):
    """The 5×5 median of ``img`` around pixel (x, y) lies within ``j`` of ``d``
    (:func:`speckle_mask`)."""
    h, w = img.shape
    x0, x1 = max(x - 2, 0), max(x - 1, 0)
    x3, x4 = min(x + 1, w - 1), min(x + 2, w - 1)
    below = 0
    above = 0
    for r in range(5):  # the 5×5 neighbourhood row by row, the five reads unrolled
        row = img[min(max(y + r - 2, 0), h - 1)]
        e0, e1, e2 = (np.float64(row[x0]) - d, np.float64(row[x1]) - d,
                      np.float64(row[x]) - d)
        e3, e4 = np.float64(row[x3]) - d, np.float64(row[x4]) - d
        below += (e0 <= j) + (e1 <= j) + (e2 <= j) + (e3 <= j) + (e4 <= j)
        above += (e0 >= -j) + (e1 >= -j) + (e2 >= -j) + (e3 >= -j) + (e4 >= -j)
        # decided once both counts reach 13, or one of them no longer can
        if below >= 13 and above >= 13:
            return True
        if min(below, above) + 20 - 5 * r < 13:
            return False
    return False


def check_frames(frames: Sequence[np.ndarray], calib: RigCalibration, view: int) -> None:
    h, w = frames[0].shape[:2]
    if (w, h) != calib.camera.size:
        raise CalibrationError(
            f"view {view}: frames are {w}x{h} px but the calibration's camera is "
            f"{calib.camera.width}x{calib.camera.height} px; use the calibration of this camera "
            "at this resolution.")


def solve_pixels(corr: Correspondence, calib: RigCalibration, processing: Mapping[str, Any],
                 to_frame: np.ndarray | None = None, depth_image: bool = False,
                 columns: np.ndarray | None = None) -> ImageSolve:
    """Solve every valid pixel of a correspondence (points in the camera frame, or in the frame
    of the (3, 4) affine map ``to_frame``), kept or not (:func:`solve_image`; ``depth_image``:
    with the speckle test's depth image; ``columns``: only these columns of each row, the
    other pixels counted as ``skipped``)."""
    return solve_image(corr.valid, corr.column, corr.row, calib,
                       row_tolerance_px=processing["row_tolerance_px"],
                       min_ray_angle_deg=processing["min_ray_angle_deg"], to_frame=to_frame,
                       depth_image=depth_image, columns=columns)


def triangulate_correspondence(corr: Correspondence, calib: RigCalibration,
                               processing: Mapping[str, Any]
                               ) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """Triangulate every valid pixel of a correspondence.

    Returns the camera pixels (N, 2) (x, y) kept, their camera-frame points (N, 3) in mm, and
    the counts ``triangulated``, ``row_rejected``, ``grazing``."""
    sol = solve_pixels(corr, calib, processing)
    pixels, points = select(sol.kept, sol.pixels, sol.points)
    return pixels, points, sol.counts


def sample_frame_map(calib: RigCalibration, angle_deg: float) -> np.ndarray:
    """(3, 4) affine map [A | b] from the camera frame to the sample frame at stage angle θ
    (degrees): ``p_sample = A @ p + b``, as :meth:`RigCalibration.camera_to_sample`."""
    a = calib.sample_rotation(angle_deg).T
    return np.column_stack([a, -a @ calib.axis_point])


#: Pixel losses in the order they happen, with what each means and what would fix it.
LOSSES: dict[str, str] = {
    "shadow": "white − black is below the decoder's shadow_threshold: the projector does not "
              "light these pixels or the frames are too dark (check the exposure, and the "
              "layout's order: are 'white' and 'black' where it says?)",
    "low_contrast": "pattern and inverse differ by less than min_contrast: check focus, the "
                    "layout's order and inverse, and the decoder's min_contrast",
    "uncertain": "the robust classification could not decide a bit (direct light too weak "
                 "against the global light or the noise) and no adaptive rescue took the "
                 "pixel: check focus and exposure, the layout's order and inverse; where "
                 "\"robust\" is set, decode with classification = \"adaptive\" (the "
                 "default: robust, plus the pixels whose bits clear the camera noise and the "
                 "global light) or, on captures without global light, "
                 "\"contrast\" — in the layout's [decoder] or the profile's [coding.settings]",
    "out_of_range": "the decoded code lies outside the projector: check projector_width / "
                    "projector_height, centred and the polarity (bright_is_one) of the layout",
    "ray_outside_roi": "the camera ray misses [processing.roi] (not triangulated: its point "
                       "would lie outside the region wherever it fell): check [processing.roi] "
                       "(radius_mm, z_min_mm, z_max_mm) against the sample's size and the "
                       "calibration's turntable axis",
    "row_rejected": "the decoded column and row do not meet in one point (more than "
                    "row_tolerance_px apart): the calibration does not belong to this rig "
                    "(camera–projector pose, projector size) or the layout swaps columns and rows",
    "outside_roi": "points outside [processing.roi]",
    "speckle": "isolated depths removed by the speckle filter (max_depth_jump_mm)",
}


def note_text(key: str, pct: float) -> str:
    """One note of :func:`dotshell.pipeline.decode_quality.view_notes`: the loss (``pct`` % of
    the image, :data:`LOSSES`) or the reversals (``pct`` % of the decoded pixels), what it
    means and what would fix it."""
    if key == "reversals":
        return f"neighbour reversals ({pct:.2f} % of the decoded pixels): {WRONG_CODES}"
    return f"{key.replace('_', ' ')} ({pct:.1f} %): {LOSSES[key]}"


def baseline_direction(calib: RigCalibration) -> str:
    """Where the projector sits seen from the camera, e.g. ``"81 mm above the camera (90° from
    the image's x axis)"`` (image x to the right, image up = camera −y)."""
    c = calib.projector_centre
    across = float(np.hypot(c[0], c[1]))
    angle = float(np.degrees(np.arctan2(-c[1], c[0])))
    steep = abs(np.sin(np.radians(angle)))
    vertical = "above" if angle > 0 else "below"
    side = ("beside" if steep <= 0.5 else vertical if steep >= np.sin(np.radians(60))
            else f"diagonally {vertical}")
    return f"{across:.0f} mm {side} the camera ({angle:.0f}° from the image's x axis)"


def explain_grazing(calib: RigCalibration, has_rows: bool, min_angle_deg: float) -> str:
    if not has_rows:
        return (f"camera rays meet the projector's column planes at less than {min_angle_deg:g}°: "
                f"the projector is {baseline_direction(calib)}, and a column plane fixes depth "
                "only when the projector is beside the camera. Decode the rows too (a coding "
                "with axes = \"both\", a layout whose order has 'rows'): dotshell then "
                "triangulates from columns and rows together")
    return (f"camera and projector rays meet at less than {min_angle_deg:g}° (the projector is "
            f"{baseline_direction(calib)}): the baseline is too short for this distance, or the "
            "calibration's camera–projector pose is not this rig's")


def no_points_error(where: str, stats: dict[str, int], calib: RigCalibration, has_rows: bool,
                    min_angle_deg: float) -> ReconstructionError:
    """The error for a sequence that gave no point: every pixel count, then the cause — the
    triangulation's largest loss when pixels were decoded (the region of interest when every
    decoded pixel's ray missed it), else the decoder's — and its fix."""
    counts = {k: int(stats.get(k, 0)) for k in ("shadow", "low_contrast", "uncertain",
                                                 "out_of_range", "ray_outside_roi", "grazing",
                                                 "row_rejected")}
    decoded = int(stats.get("decoded", 0))
    solve = ("grazing", "row_rejected")
    stage = (("shadow", "low_contrast", "uncertain", "out_of_range") if not decoded
             else solve if any(counts[k] for k in solve) else ("ray_outside_roi",))
    worst = max(stage, key=counts.__getitem__)
    why = (explain_grazing(calib, has_rows, min_angle_deg) if worst == "grazing"
           else LOSSES[worst])
    listing = ", ".join(f"{k} {v}" for k, v in counts.items() if v)
    cause = (f"the decoded pixels were lost to {worst} ({counts[worst]} px)" if decoded
             else f"nothing was decoded; the largest loss is {worst} ({counts[worst]} px)")
    return ReconstructionError(
        f"{where}: no pixel decoded into a point. Of {stats.get('pixels', 0)} pixels {decoded} "
        f"were decoded; lost: {listing or 'none'}. Cause: {cause}: {why}.")


def reconstruct_view(view: int, angle_deg: float, frames: Sequence[np.ndarray],
                     coding: PatternCoding, calib: RigCalibration,
                     processing: Mapping[str, Any]) -> ViewCloud:
    """Decode one view's frames and triangulate them into sample-frame points (mm). Only the
    pixels whose camera rays can meet the region of interest are triangulated
    (:func:`~dotshell.geometry.roi_rays.roi_columns`: the same points kept, bit for bit); the
    others are counted as ``ray_outside_roi``."""
    check_frames(frames, calib, view)
    t0 = time.perf_counter()
    corr = coding.decode(frames, calib.projector.size)
    t1 = time.perf_counter()
    roi = processing["roi"]
    tri = solve_pixels(corr, calib, processing, sample_frame_map(calib, angle_deg),
                       depth_image=processing["max_depth_jump_mm"] > 0,
                       columns=roi_columns(calib, roi["radius_mm"], roi["z_min_mm"],
                                           roi["z_max_mm"]))
    pixels, points, counts = view_points(tri, frames[0].shape[:2],
                                         processing["max_depth_jump_mm"], roi)
    stats = {**corr.stats, "ray_outside_roi": tri.skipped, **tri.counts, **counts}
    t3 = time.perf_counter()
    quality = view_quality(corr)
    t4 = time.perf_counter()
    return ViewCloud(view, angle_deg, points, pixels, corr, stats,
                     {"decode": t1 - t0, "triangulate": t3 - t1, "quality": t4 - t3}, quality)
