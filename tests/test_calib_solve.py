"""The pure calibration solvers on synthetic correspondences with known truth (no renderer)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from dotshell.calibration.board import Board
from dotshell.calibration.solve import (OutlierRule, PoseData, calibrate_lens, calibrate_stereo,
                                        projector_corners, turntable_axis)
from dotshell.errors import CalibrationError
from dotshell.geometry.lens import Lens

BOARD = Board("checkerboard", 10, 7, 10.0)
CAM = Lens(np.array([[1500.0, 0, 655.0], [0, 1500.0, 500.0], [0, 0, 1]]),
           np.array([-0.1, 0.05, 0, 0, 0]), 1280, 1024)
PROJ = Lens(np.array([[1800.0, 0, 520.0], [0, 1800.0, 700.0], [0, 0, 1]]),
            np.array([-0.05, 0, 0, 0, 0]), 1024, 768)
R_CP = cv2.Rodrigues(np.array([0.02, -0.35, 0.01]))[0]
T_CP = np.array([-150.0, 3.0, 40.0])


def _pose(k: int) -> tuple[np.ndarray, np.ndarray]:
    """Board → camera pose k: the board ~400 mm away, tilted by up to ±35°."""
    rng = np.random.default_rng(k)
    rvec = np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6), rng.uniform(-0.3, 0.3)])
    R = cv2.Rodrigues(rvec)[0]
    t = np.array([rng.uniform(-30, 30), rng.uniform(-20, 20), 400 + rng.uniform(-50, 50)])
    return R, t - R @ BOARD.centre


def _views(n: int, noise_px: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    obj = BOARD.object_points()
    cam, proj = [], []
    for k in range(n):
        R, t = _pose(k)
        Xc = obj @ R.T + t
        cam.append(PoseData(f"pose_{k:02d}", obj, CAM.project(Xc) + rng.normal(0, noise_px, (len(obj), 2))))
        proj.append(PoseData(f"pose_{k:02d}", obj,
                             PROJ.project(Xc @ R_CP.T + T_CP) + rng.normal(0, noise_px, (len(obj), 2))))
    return cam, proj


def test_lens_and_stereo_recovered_and_outlier_named():
    cam_poses, proj_poses = _views(10, 0.05)
    cam_poses[3].image_points = cam_poses[3].image_points + np.random.default_rng(9).normal(0, 2.0, (54, 2))
    rule = OutlierRule(min_poses=6, factor=3.0, max_rms_px=1.0)
    cam = calibrate_lens("camera", cam_poses, CAM.size, "k1k2", rule)
    assert set(cam.left_out) == {"pose_03"} and "RMS" in cam.left_out["pose_03"]
    assert cam.rms_px < 0.1
    assert cam.lens.K[0, 0] == pytest.approx(1500.0, rel=2e-3)
    assert abs(cam.lens.K[0, 2] - 655.0) < 2.0 and abs(cam.lens.K[1, 2] - 500.0) < 2.0
    assert cam.lens.dist[0] == pytest.approx(-0.1, abs=0.01)
    proj = calibrate_lens("projector", proj_poses, PROJ.size, "k1", rule, dict(cam.left_out))
    st = calibrate_stereo(cam, proj, cam_poses, proj_poses, "k1k2")
    assert "pose_03" not in st.per_pose_rms_px and len(st.per_pose_rms_px) == 9
    assert np.linalg.norm(st.T) == pytest.approx(np.linalg.norm(T_CP), rel=2e-3)
    ang = np.degrees(np.arccos(np.clip((np.trace(st.R @ R_CP.T) - 1) / 2, -1, 1)))
    assert ang < 0.2  # pp uncertainty (~1 px at f = 1500 px) tilts R by ~0.05°
    assert st.projector.K[0, 0] == pytest.approx(1800.0, rel=2e-3)


def test_too_few_good_poses_is_an_error_naming_them():
    cam_poses, _ = _views(5, 0.05)
    with pytest.raises(CalibrationError, match=r"camera: only 4 good poses.*pose_01: target not found"):
        calibrate_lens("camera", cam_poses, CAM.size, "k1", OutlierRule(min_poses=5),
                       {"pose_01": "target not found in x.png"})


def test_local_homographies_recover_projector_corners():
    """Decoded maps from a known smooth camera → projector mapping (a homography plus a weak
    quadratic term); corners come back to ~0.01 px."""
    h, w = 240, 320
    H = np.array([[1.1, 0.05, 20.0], [-0.03, 0.95, 15.0], [1e-4, -5e-5, 1.0]])
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    p = np.stack([xs, ys, np.ones_like(xs)], -1) @ H.T
    col = p[..., 0] / p[..., 2] + 2e-5 * (xs - 160) ** 2
    row = p[..., 1] / p[..., 2]
    valid = np.ones((h, w), bool)
    valid[:, 100:104] = False  # a stripe of undecoded pixels
    valid[0:40, 280:320] = False  # a shadow
    corners = np.array([[50.3, 60.7], [101.2, 120.9], [250.5, 200.1], [300.0, 20.0]])
    out, ok = projector_corners(corners, col.astype(np.float32), row.astype(np.float32), valid, 12)
    assert ok.tolist() == [True, True, True, False]  # the corner in the shadow has no pixels
    q = np.column_stack([corners, np.ones(4)]) @ H.T
    truth = np.column_stack([q[:, 0] / q[:, 2] + 2e-5 * (corners[:, 0] - 160) ** 2, q[:, 1] / q[:, 2]])
    assert np.abs(out[:3] - truth[:3]).max() < 0.02


def test_turntable_axis_from_board_at_stage_angles():
    d = np.array([0.0, -0.97, -0.25])
    d /= np.linalg.norm(d)
    plate = np.array([5.0, 60.0, 420.0])
    height = 30.0
    R0 = cv2.Rodrigues(np.array([0.5, 0.1, 0.05]))[0]
    centre = plate + d * height + np.array([8.0, 0, 0])
    t0 = centre - R0 @ BOARD.centre
    obj = BOARD.object_points()
    rng = np.random.default_rng(1)
    rows = []
    for k, a in enumerate((-40.0, -20.0, 0.0, 20.0, 40.0)):
        Ra = cv2.Rodrigues(d * np.deg2rad(a))[0]
        # the board turns about the axis through the plate point
        X = (obj @ R0.T + t0 - plate) @ Ra.T + plate
        rows.append((f"turntable_{k}", a, np.arange(len(obj)), CAM.project(X) + rng.normal(0, 0.05, (len(obj), 2))))
    sol = turntable_axis(CAM, obj, rows, BOARD.centre, height)
    # the foot of the board centre on the axis, lowered by the height
    foot = plate + d * ((centre - plate) @ d)
    truth_point = foot - d * height
    assert np.degrees(np.arccos(np.clip(sol.direction @ d, -1, 1))) < 0.05
    assert np.linalg.norm(sol.point - truth_point) < 0.1
    assert sol.rms_px < 0.1
    with pytest.raises(CalibrationError, match="span less than 20"):
        turntable_axis(CAM, obj, [r for r in rows if abs(r[1]) < 1] * 3, BOARD.centre, height)
