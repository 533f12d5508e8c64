"""A view triangulates only the pixels whose camera rays can meet the region of interest
(``dotshell.geometry.roi_rays``): the rows' column ranges hold every ray that meets the
cylinder, and ``reconstruct_view`` keeps the same points, bit for bit, as solving every decoded
pixel did, counting the others as ``ray_outside_roi``."""

from __future__ import annotations

import numpy as np
import pytest
from test_decode_quality import _decoded_view

from dotshell.geometry.calibration import RigCalibration
from dotshell.geometry.roi_rays import REACH_PX, roi_columns
from dotshell.geometry.triangulate import camera_ideal_grid
from dotshell.pipeline.reconstruct import (in_roi, no_points_error, reconstruct_view,
                                           sample_frame_map, solve_pixels, view_points)
from dotshell.pipeline.scan import load_run_profile
from dotshell.run.layout import RunLayout
from dotshell.run.store import RunStore


def _view(run, pm, view: int):
    store = RunStore.open(run)
    calib = RigCalibration.load(store.path(RunLayout.CALIBRATION))
    angle = float(store.manifest["views"][view]["angle_deg"])
    return _decoded_view(run, pm, view), calib, angle, load_run_profile(store, pm).processing


def _inside_somewhere(calib: RigCalibration, roi: dict, samples: int = 4000) -> np.ndarray:
    """(H, W) bool: some point of the pixel's camera ray, sampled every ~0.1 mm over the
    depths that can reach the cylinder, lies inside it (the definition, by brute force)."""
    xy = camera_ideal_grid(calib.camera)
    h, w = xy.shape[:2]
    reach = np.linalg.norm(calib.axis_point) + roi["radius_mm"] + roi["z_max_mm"]
    basis = calib.stage_basis()
    hit = np.zeros((h, w), bool)
    for s in np.linspace(1.0, reach, samples):
        cam = np.concatenate([xy * s, np.full((h, w, 1), s)], axis=2) - calib.axis_point
        p = cam @ basis.T
        hit |= ((p[..., 0] ** 2 + p[..., 1] ** 2 <= roi["radius_mm"] ** 2)
                & (p[..., 2] >= roi["z_min_mm"]) & (p[..., 2] <= roi["z_max_mm"]))
    return hit


def test_column_ranges_hold_every_ray_that_meets_the_roi(small_scan, pm):
    """Every pixel with a sampled ray point inside the cylinder lies in its row's range, and
    (its 5×5 neighbourhood too) the range reaches REACH_PX beyond; the ranges leave out a
    share of the image (the view of the bench sees 75 % of it through the region)."""
    _, calib, _, processing = _view(small_scan[0].run_dir, pm, 0)
    roi = dict(processing["roi"])
    cols = roi_columns(calib, roi["radius_mm"], roi["z_min_mm"], roi["z_max_mm"])
    hit = _inside_somewhere(calib, roi)
    h, w = hit.shape
    assert cols.shape == (h, 2) and not cols.flags.writeable
    x = np.arange(w)
    in_range = (x >= cols[:, :1]) & (x < cols[:, 1:])
    near = hit.copy()  # the hits' 5×5 neighbourhoods
    for dy in range(-REACH_PX, REACH_PX + 1):
        for dx in range(-REACH_PX, REACH_PX + 1):
            near[max(dy, 0):h + min(dy, 0), max(dx, 0):w + min(dx, 0)] |= \
                hit[max(-dy, 0):h + min(-dy, 0), max(-dx, 0):w + min(-dx, 0)]
    assert hit.sum() > 1000 and np.all(in_range[near])
    assert 0.05 < 1 - in_range.mean() < 0.95
    assert roi_columns(calib, roi["radius_mm"], roi["z_min_mm"], roi["z_max_mm"]) is cols
    everything = roi_columns(calib, np.inf, roi["z_min_mm"], roi["z_max_mm"])
    assert np.all(everything == [0, w])


@pytest.mark.parametrize("view", [0, 3])
def test_a_view_keeps_the_same_points_as_solving_every_pixel(small_scan, pm, view):
    """``reconstruct_view`` (pixels outside the ranges not solved) against every decoded pixel
    solved and then kept by the region and the speckle test: the same points and pixels, bit
    for bit; the pixels skipped are those outside the ranges, every one of which the full
    solve either rejected or put outside the region."""
    corr, calib, angle, processing = _view(small_scan[0].run_dir, pm, view)
    roi = processing["roi"]
    assert processing["max_depth_jump_mm"] > 0  # the speckle test's depth image is compared

    class Decoded:
        def decode(self, frames, projector_size):
            return corr

    h, w = corr.valid.shape
    frames = [np.zeros((h, w), np.uint16)] * 2
    got = reconstruct_view(view, angle, frames, Decoded(), calib, processing)
    full = solve_pixels(corr, calib, processing, sample_frame_map(calib, angle),
                        depth_image=True)
    pixels, points, counts = view_points(full, (h, w), processing["max_depth_jump_mm"], roi)
    assert np.array_equal(got.pixels, pixels) and np.array_equal(got.points, points)
    cols = roi_columns(calib, roi["radius_mm"], roi["z_min_mm"], roi["z_max_mm"])
    px = full.pixels
    skipped = (px[:, 0] < cols[px[:, 1], 0]) | (px[:, 0] >= cols[px[:, 1], 1])
    kept_inside = full.kept & in_roi(np.nan_to_num(full.points, nan=np.inf), roi)
    assert got.stats["ray_outside_roi"] == np.count_nonzero(skipped) > 0
    assert not np.any(kept_inside & skipped)
    assert got.stats["outside_roi"] == counts["outside_roi"] - np.count_nonzero(full.kept
                                                                               & skipped)
    assert got.stats["triangulated"] == full.counts["triangulated"] - np.count_nonzero(
        full.kept & skipped)
    assert got.stats["speckle"] == counts["speckle"] and got.stats["points"] == len(points)


def test_no_point_because_every_ray_missed_the_roi_names_the_roi():
    """Every decoded pixel's ray missed the region: the error says so and how to fix it; a
    triangulation loss among the pixels that were solved is named before it."""
    stats = {"pixels": 1000, "decoded": 400, "shadow": 600, "ray_outside_roi": 400}
    msg = str(no_points_error("run", stats, None, True, 5.0))  # type: ignore[arg-type]
    assert "lost to ray_outside_roi (400 px)" in msg and "[processing.roi]" in msg
    msg = str(no_points_error("run", {**stats, "ray_outside_roi": 300, "row_rejected": 100},
                              None, True, 5.0))  # type: ignore[arg-type]
    assert "lost to row_rejected (100 px)" in msg and "ray_outside_roi 300" in msg
