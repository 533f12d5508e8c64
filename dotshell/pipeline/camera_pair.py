"""Two cameras sharing one projector that is NOT calibrated: each camera's capture sequence is
decoded through its layout, the projector codes pair the cameras' pixels, and the points come
from the two cameras' rays (:mod:`dotshell.geometry.code_stereo`), with the cameras' pair
calibration (``dotshell calibrate --camera-pair``). Writes ``cloud.ply`` (camera 1's frame,
mm) and ``report.json`` into ``<out>/<time>_camera-pair-<layout>/``.

With the projector calibrated too (camera 1's camera–projector calibration), every matched pixel
is solved three ways along camera 1's ray — camera–projector, camera–camera and both fused by
least squares (:mod:`dotshell.geometry.ray_fusion`) — and ``cloud.ply`` holds the fused points,
``camera-projector.ply`` and ``camera-camera.ply`` the single estimates of the same pixels.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from dotshell.errors import CalibrationError
from dotshell.pipeline.captures import CapturesResult
from dotshell.run.capture_layouts import load_layout, read_sequence
from dotshell.run.layout import RunLayout

#: Matched rays passing further apart than this (mm) are dropped (a wrong match or code).
MAX_RAY_GAP_MM = 0.2


def reconstruct_camera_pair(captures1: Path | str, captures2: Path | str,
                            pair_file: Path | str, layout1: Path | str,
                            layout2: Path | str | None, pm,
                            out_dir: Path | str = "runs",
                            calibration: Path | str | None = None) -> CapturesResult:
    """Decode both sequences, match them by projector code and triangulate camera 1 against
    camera 2; ``layout2`` defaults to ``layout1``. With ``calibration`` (camera 1 and the
    projector: ``calibration.json`` or an OpenCV file) the camera–projector and camera–camera
    points are fused (:func:`fuse_with_projector`)."""
    from dotshell.calibration.camera_only import load_camera_pair
    from dotshell.geometry.code_stereo import match_by_codes, triangulate_pair
    from dotshell.pipeline.decode_quality import view_quality
    from dotshell.run.ply import write_ply
    from dotshell.run.store import RunStore

    pair = load_camera_pair(pair_file)
    calib = None if calibration is None else load_projector_calibration(calibration, pair,
                                                                         pair_file)
    t0 = time.perf_counter()
    decoded = []
    for captures, lay, lens in ((captures1, layout1, pair.camera1),
                                (captures2, layout2 or layout1, pair.camera2)):
        layout = load_layout(lay)
        seq = read_sequence(captures, layout, pm)
        if seq.camera_size != lens.size:
            w, h = seq.camera_size
            raise CalibrationError(f"{captures}: frames are {w}x{h} px but the camera pair's "
                                   f"camera is {lens.width}x{lens.height} px ({pair_file}).")
        corr = seq.coding.decode(seq.frames, layout.projector_size)
        if corr.row is None:
            raise CalibrationError(f"{captures}: layout {layout.name!r} decodes no rows; two "
                                   "cameras are matched by projector column AND row.")
        if calib is not None and layout.projector_size != tuple(calib.projector.size):
            raise CalibrationError(
                f"the calibration's projector is {calib.projector.width}x"
                f"{calib.projector.height} px but layout {layout.name!r} says "
                f"{layout.projector_size[0]}x{layout.projector_size[1]} px; set "
                f"projector_width/height in {layout.source} to the projector the frames were "
                "made with.")
        decoded.append((layout, corr))
    t1 = time.perf_counter()
    (lay1, c1), (_, c2) = decoded
    pix1, pix2 = match_by_codes(c1.column, c1.row, c1.valid, c2.column, c2.row, c2.valid)
    points, gap = triangulate_pair(pair.camera1, pair.camera2, pair.R, pair.T, pix1, pix2)
    keep = np.isfinite(gap) & (gap <= MAX_RAY_GAP_MM) & (points[:, 2] > 0)
    singles: dict[str, np.ndarray] = {}
    fusion: dict[str, Any] | None = None
    if calib is not None:
        points, singles, fusion, keep = fuse_with_projector(calib, pair, c1, c2, pix1, pix2,
                                                            keep)
    t2 = time.perf_counter()
    store = RunStore.create(Path(out_dir), f"camera-pair-{lay1.name}")
    write_ply(store.path(RunLayout.CLOUD), points[keep])
    for name, pts in singles.items():
        write_ply(store.path(f"{name}.ply"), pts[keep])
    report: dict[str, Any] = {
        "captures": [str(Path(c).resolve()) for c in (captures1, captures2)],
        "camera_pair": str(Path(pair_file).resolve()), "frame": "camera 1 (mm)",
        "decode": [c1.stats, c2.stats], "quality": [view_quality(c1), view_quality(c2)],
        "matches": int(len(pix1)),
        "ray_gap_mm": {"median": float(np.median(gap)) if len(gap) else None,
                       "dropped_over": MAX_RAY_GAP_MM, "dropped": int((~keep).sum())},
        "cloud": {"path": RunLayout.CLOUD, "points": int(keep.sum())},
        **({"fusion": fusion} if fusion is not None else {}),
        "timings_s": {"read_decode": round(t1 - t0, 3), "match_triangulate": round(t2 - t1, 3)},
    }
    store.write_json(RunLayout.REPORT, report)
    store.close()
    return CapturesResult(store.root, report)


def load_projector_calibration(calibration: Path | str, pair, pair_file: Path | str):
    """Camera 1's camera–projector calibration for fusing (any file ``reconstruct --captures``
    reads); refused when its camera is not camera 1's size."""
    from dotshell.geometry.opencv_io import load_any_calibration

    calib = load_any_calibration(calibration)
    if tuple(calib.camera.size) != tuple(pair.camera1.size):
        raise CalibrationError(
            f"{calibration}: its camera is {calib.camera.width}x{calib.camera.height} px but "
            f"camera 1 of {pair_file} is {pair.camera1.width}x{pair.camera1.height} px; give "
            "the camera–projector calibration of camera 1 (the --captures camera).")
    return calib


def fuse_with_projector(calib, pair, c1, c2, pix1: np.ndarray, pix2: np.ndarray,
                        keep: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray],
                                                   dict[str, Any], np.ndarray]:
    """Fused points (N, 3) of the matched pixels, the single estimates by name, the report's
    ``fusion`` section and the points kept: the camera–camera checks (``keep``) and the
    camera–projector ones (row consistency, grazing rays) must both pass. Camera 1's rays and
    the projector pose come from ``calib``, camera 2's pose from the pair, moved into
    ``calib``'s camera frame (:func:`frame_rotation` of the two solves of camera 1)."""
    from dotshell.geometry.ray_fusion import (
        frame_rotation,
        fuse_camera_pair,
        pixels_per_code,
    )
    from dotshell.geometry.triangulate import triangulate

    x, y = pix1[:, 0].astype(int), pix1[:, 1].astype(int)
    col, row = c1.column[y, x].astype(np.float64), c1.row[y, x].astype(np.float64)
    rays1 = calib.camera.rays(pix1)
    checked = triangulate(rays1, col, calib, row)
    scale = pixels_per_code(c2.column, c2.row, c2.valid)
    turn = frame_rotation(calib.camera, pair.camera1)
    fused = fuse_camera_pair(rays1, calib.projector.undistort(np.column_stack([col, row])),
                             pair.camera2.undistort(pix2), (calib.R, calib.T),
                             (pair.R @ turn, pair.T),
                             np.diag(calib.projector.K)[:2], np.diag(pair.camera2.K)[:2], scale)
    keep = keep & checked.keep & np.isfinite(fused.fused).all(axis=1) & (fused.fused[:, 2] > 0)
    differ = np.linalg.norm(fused.camera_projector - fused.camera_camera, axis=1)[keep]
    report = {"projector_calibration": str(calib.source),
              "camera2_px_per_projector_px": round(scale, 4),
              "camera1_frames_apart_deg": round(float(np.degrees(np.arccos(np.clip(
                  (np.trace(turn) - 1.0) / 2.0, -1.0, 1.0)))), 5),
              "camera2_sigma_code_units": round(fused.camera2_sigma_px, 4),
              "depth_sigma_ratio_camera_camera_over_projector": round(fused.depth_sigma_ratio, 4),
              "single_estimates_median_apart_mm":
                  float(np.median(differ)) if len(differ) else None,
              "camera_projector_rejected": int(np.count_nonzero(~checked.keep))}
    return (fused.fused, {"camera-projector": fused.camera_projector,
                          "camera-camera": fused.camera_camera}, report, keep)
