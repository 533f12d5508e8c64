"""The per-point masks of ``reconstruct_view`` against their definitions: the speckle test is
OpenCV's 5×5 median of the depth image, the region of interest a cylinder in the sample frame."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dotshell.pipeline.reconstruct import in_roi, keep_in_roi, speckle_mask


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


def test_kept_points_are_smooth_and_inside_and_every_loss_is_counted_once() -> None:
    rng = np.random.default_rng(5)
    n = 50_000
    pts = rng.uniform(-30, 30, (n, 3))
    kept = rng.random(n) < 0.8
    pts[~kept] = np.nan  # as the solve leaves the points it did not keep
    smooth = kept & (rng.random(n) < 0.9)
    roi = {"radius_mm": 20.0, "z_min_mm": -10.0, "z_max_mm": 25.0}
    keep, counts = keep_in_roi(kept, smooth, pts, roi)
    inside = in_roi(pts, roi)
    assert np.array_equal(keep, smooth & inside)
    assert counts == {"speckle": int(np.count_nonzero(kept & ~smooth)),
                      "outside_roi": int(np.count_nonzero(smooth & ~inside)),
                      "points": int(np.count_nonzero(keep))}
    assert counts["speckle"] + counts["outside_roi"] + counts["points"] == kept.sum()


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
