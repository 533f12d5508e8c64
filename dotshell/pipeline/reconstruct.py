"""Per-view reconstruction: decode frames → triangulate → sample frame → region of interest."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Sequence

import cv2
import numpy as np

from dotshell.coding import Correspondence, PatternCoding
from dotshell.errors import CalibrationError
from dotshell.geometry.calibration import RigCalibration
from dotshell.geometry.triangulate import camera_ray_grid, triangulate


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


def in_roi(points: np.ndarray, roi: dict[str, float]) -> np.ndarray:
    """Mask of sample-frame points (N, 3) inside the cylindrical region of interest."""
    r = np.hypot(points[:, 0], points[:, 1])
    return (r <= roi["radius_mm"]) & (points[:, 2] >= roi["z_min_mm"]) & (
        points[:, 2] <= roi["z_max_mm"])


def speckle_mask(pixels: np.ndarray, depth_mm: np.ndarray, shape: tuple[int, int],
                 max_jump_mm: float) -> np.ndarray:
    """True for points whose depth agrees with the median of their 5×5 camera neighbourhood
    within ``max_jump_mm`` (isolated decoding errors — speckles — fail). Pixels without
    points count as depth 0, so a point needs mostly valid neighbours to pass."""
    img = np.zeros(shape, np.float32)
    img[pixels[:, 1], pixels[:, 0]] = depth_mm
    med = cv2.medianBlur(img, 5)
    return np.abs(med[pixels[:, 1], pixels[:, 0]] - depth_mm) <= max_jump_mm


def check_frames(frames: Sequence[np.ndarray], calib: RigCalibration, view: int) -> None:
    h, w = frames[0].shape[:2]
    if (w, h) != calib.camera.size:
        raise CalibrationError(
            f"view {view}: frames are {w}x{h} px but the calibration's camera is "
            f"{calib.camera.width}x{calib.camera.height} px; use the calibration of this camera "
            "at this resolution.")


def triangulate_correspondence(corr: Correspondence, calib: RigCalibration,
                               processing: dict[str, Any]
                               ) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """Triangulate every valid pixel of a correspondence.

    Returns the camera pixels (N, 2) (x, y) kept, their camera-frame points (N, 3) in mm, and
    the counts ``triangulated``, ``row_rejected``, ``grazing``."""
    ys, xs = np.nonzero(corr.valid)
    rays = camera_ray_grid(calib.camera)[ys, xs]
    tri = triangulate(rays, corr.column[ys, xs], calib,
                      row=None if corr.row is None else corr.row[ys, xs],
                      row_tolerance_px=processing["row_tolerance_px"],
                      min_ray_angle_deg=processing["min_ray_angle_deg"])
    stats = {"triangulated": int(tri.keep.sum()), "row_rejected": int(tri.row_rejected.sum()),
             "grazing": int(tri.grazing.sum())}
    return np.column_stack([xs, ys])[tri.keep], tri.points[tri.keep], stats


def reconstruct_view(view: int, angle_deg: float, frames: Sequence[np.ndarray],
                     coding: PatternCoding, calib: RigCalibration,
                     processing: dict[str, Any]) -> ViewCloud:
    """Decode one view's frames and triangulate them into sample-frame points (mm)."""
    check_frames(frames, calib, view)
    t0 = time.perf_counter()
    corr = coding.decode(frames, calib.projector.size)
    t1 = time.perf_counter()
    pixels, cam_pts, tri_stats = triangulate_correspondence(corr, calib, processing)
    smooth = np.ones(len(cam_pts), bool)
    if processing["max_depth_jump_mm"] > 0:
        smooth = speckle_mask(pixels, cam_pts[:, 2], frames[0].shape[:2],
                              processing["max_depth_jump_mm"])
    pts = calib.camera_to_sample(cam_pts[smooth], angle_deg)
    pixels = pixels[smooth]
    inside = in_roi(pts, processing["roi"])
    t2 = time.perf_counter()
    stats = {**corr.stats, **tri_stats, "speckle": int((~smooth).sum()),
             "outside_roi": int((~inside).sum()), "points": int(inside.sum())}
    return ViewCloud(view, angle_deg, pts[inside], pixels[inside], corr, stats,
                     {"decode": t1 - t0, "triangulate": t2 - t1})
