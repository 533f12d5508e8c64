"""The per-point masks of ``reconstruct_view`` against their definitions: the speckle test is
OpenCV's 5×5 median of the depth image, the region of interest a cylinder in the sample frame."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dotshell.geometry.triangulate import ImageSolve
from dotshell.runtime import parallel
from dotshell.pipeline.reconstruct import in_roi, keep_points, speckle_mask, view_points


def _depth_scene(seed: int, shape: tuple[int, int] = (60, 80)) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) (x, y) and depths (mm) of a smooth surface with holes, speckles, steps
    and values sitting exactly on the test's threshold."""
    rng = np.random.default_rng(seed)
    h, w = shape
    y, x = np.mgrid[0:h, 0:w]
    depth = 300.0 + 0.05 * x + 0.02 * y + (x > w // 2) * 3.0
    have = rng.random(shape) > 0.25
    have[:, :3] = rng.random((h, 3)) > 0.6  # sparse near the border (replicated there)
    speckles = rng.random(shape) < 0.05
    depth = np.where(speckles, depth + rng.normal(0, 20, shape), depth)
    depth = np.where(rng.random(shape) < 0.05, np.round(depth), depth)  # ties at the threshold
    ys, xs = np.nonzero(have)
    return np.column_stack([xs, ys]).astype(np.int32), depth[ys, xs]


def _speckle_by_median(pixels: np.ndarray, depth: np.ndarray, shape: tuple[int, int],
                       jump: float) -> np.ndarray:
    img = np.zeros(shape, np.float32)
    img[pixels[:, 1], pixels[:, 0]] = depth
    median = cv2.medianBlur(img, 5)
    return np.abs(median[pixels[:, 1], pixels[:, 0]].astype(np.float64) - depth) <= jump


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("jump", [0.5, 1.0, 2.0])
def test_speckle_mask_is_the_5x5_median_test(seed: int, jump: float) -> None:
    pixels, depth = _depth_scene(seed)
    got = speckle_mask(pixels, depth, (60, 80), jump)
    want = _speckle_by_median(pixels, depth, (60, 80), jump)
    assert 0 < np.count_nonzero(~want) < len(want)  # the scene has speckles and surface
    assert np.array_equal(got, want)


def test_roi_is_the_cylinder() -> None:
    rng = np.random.default_rng(3)
    pts = rng.uniform(-30, 30, (20000, 3))
    pts[:10] = [[10.0, 0, 0], [0, -10.0, 0], [6.0, 8.0, 0], [0, 0, 5.0], [0, 0, -5.0],
                [10.000001, 0, 0], [0, 0, 5.000001], [7.0710678, 7.0710678, 0], [0, 0, 0],
                [np.nan, 0, 0]]
    roi = {"radius_mm": 10.0, "z_min_mm": -5.0, "z_max_mm": 5.0}
    got = in_roi(pts, roi)
    want = (np.hypot(pts[:, 0], pts[:, 1]) <= 10.0) & (pts[:, 2] >= -5.0) & (pts[:, 2] <= 5.0)
    assert got[:10].tolist() == [True, True, True, True, True, False, False, True, True, False]
    assert np.array_equal(got, want)


@pytest.mark.parametrize("jump", [0.5, 0.0])
def test_kept_points_are_smooth_and_inside_and_every_loss_is_counted_once(jump: float) -> None:
    """The speckle test's depth image holds every solved point, inside the region or not;
    a point outside is counted outside, a point inside failing the test a speckle
    (``jump`` 0: no speckle test)."""
    pixels, depth = _depth_scene(5)
    n = len(depth)
    rng = np.random.default_rng(5)
    kept = rng.random(n) < 0.9
    pts = np.column_stack([pixels[:, 0] - 40.0, pixels[:, 1] - 30.0, depth - 300.0])
    pts[~kept] = np.nan  # as the solve leaves the points it did not keep
    depth = np.where(kept, depth, np.nan)
    roi = {"radius_mm": 30.0, "z_min_mm": -10.0, "z_max_mm": 3.5}
    sol = ImageSolve(pixels, pts, depth, kept, {})
    keep, counts = keep_points(sol, (60, 80), jump, roi)
    inside = in_roi(pts, roi)
    smooth = speckle_mask(pixels, depth, (60, 80), jump, kept) if jump > 0 else kept
    assert np.array_equal(keep, kept & inside & smooth)
    assert counts == {"outside_roi": int(np.count_nonzero(kept & ~inside)),
                      "speckle": int(np.count_nonzero(kept & inside & ~smooth)),
                      "points": int(np.count_nonzero(keep))}
    assert counts["speckle"] + counts["outside_roi"] + counts["points"] == kept.sum()
    assert min(counts.values()) > 0 if jump > 0 else counts["speckle"] == 0


@pytest.mark.parametrize("threads", [1, 2])
def test_view_points_gathers_the_kept_points_in_order_band_by_band(threads: int) -> None:
    """~90 000 solved pixels: four bands on two threads, each copying its kept points after
    the bands before it."""
    pixels, depth = _depth_scene(7, (300, 400))
    rng = np.random.default_rng(7)
    kept = rng.random(len(depth)) < 0.9
    pts = np.column_stack([pixels[:, 0] - 200.0, pixels[:, 1] - 150.0, depth - 300.0])
    pts[~kept] = np.nan
    sol = ImageSolve(pixels, pts, np.where(kept, depth, np.nan), kept, {})
    roi = {"radius_mm": 220.0, "z_min_mm": -10.0, "z_max_mm": 20.0}
    with parallel.threads(threads):
        keep, counts = keep_points(sol, (300, 400), 0.5, roi)
        got_pixels, got_points, got_counts = view_points(sol, (300, 400), 0.5, roi)
    assert got_counts == counts and 0 < counts["points"] < len(depth) - 1000
    assert got_pixels.dtype == np.int32 and np.array_equal(got_pixels, pixels[keep])
    assert np.array_equal(got_points, pts[keep])


def test_select_is_boolean_indexing_done_in_place() -> None:
    from dotshell.geometry.triangulate import select

    rng = np.random.default_rng(3)
    n = 100_000
    mask = rng.random(n) < 0.7
    pixels = rng.integers(0, 1000, (n, 2)).astype(np.int32)
    points = rng.random((n, 3))
    got = select(mask, pixels.copy(), points.copy())
    for g, a in zip(got, (pixels, points)):
        assert g.dtype == a.dtype and np.array_equal(g, a[mask])
    assert select(np.zeros(n, bool), points.copy())[0].shape == (0, 3)


@pytest.mark.parametrize("seed", range(4))
def test_the_speckle_tests_shortcut_decides_as_the_full_count(seed: int) -> None:
    """``keep_points`` accepts a point at once when the 15 depths of the upper three rows of
    its 5×5 neighbourhood lie within the jump; on rows of a few depth levels, some rows nearly
    empty and the image's borders, it keeps exactly the points the full count keeps
    (``speckle_mask``, itself OpenCV's median test above)."""
    rng = np.random.default_rng(seed)
    h, w = 40, 50
    level = 300.0 + rng.integers(0, 3, h)[:, None] + np.zeros((1, w))  # each row one of 3
    have = rng.random((h, w)) < rng.uniform(0.2, 1.0, h)[:, None]  # rows full to sparse
    have[:, -2:] = rng.random((h, 2)) < 0.5
    depth_img = level + rng.normal(0, 0.1, (h, w)) * (rng.random((h, w)) < 0.3)
    ys, xs = np.nonzero(have)
    pixels = np.column_stack([xs, ys]).astype(np.int32)
    depth = depth_img[ys, xs]
    kept = np.ones(len(depth), bool)
    pts = np.zeros((len(depth), 3))
    roi = {"radius_mm": 1.0, "z_min_mm": -1.0, "z_max_mm": 1.0}
    keep, counts = keep_points(ImageSolve(pixels, pts, depth, kept, {}), (h, w), 0.5, roi)
    want = speckle_mask(pixels, depth, (h, w), 0.5)
    assert counts["speckle"] > 20 and counts["points"] > 20
    assert np.array_equal(keep, want)
