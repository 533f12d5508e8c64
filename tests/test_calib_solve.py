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


def test_bundle_adjustment_refines_both_lenses_with_covariance():
    """The joint solve (camera + projector + poses + stereo pose) lands on the truth within a
    few of its own one-sigma uncertainties, and those uncertainties are of the right size."""
    from dotshell.calibration.bundle import bundle_adjust

    cam_poses, proj_poses = _views(8, 0.05, seed=3)
    rule = OutlierRule(min_poses=6, factor=3.0, max_rms_px=1.0)
    cam = calibrate_lens("camera", cam_poses, CAM.size, "k1k2", rule)
    proj = calibrate_lens("projector", proj_poses, PROJ.size, "k1k2", rule)
    st = calibrate_stereo(cam, proj, cam_poses, proj_poses, "k1k2")
    b = bundle_adjust(cam_poses, proj_poses[:6], st.camera, st.projector, st.R, st.T, cam.rvecs,
                      cam.tvecs, "k1k2")  # two poses seen by the camera only
    assert set(b.per_pose_rms_px) == {p.name for p in cam_poses}
    assert 0.04 < b.camera_rms_px < 0.09 and 0.04 < b.projector_rms_px < 0.09
    for lens, truth, name in ((b.camera, CAM, "camera"), (b.projector, PROJ, "projector")):
        sig = b.sigma[name]
        assert 0.05 < sig["cx"] < 8.0 and 0.05 < sig["fx"] < 8.0  # 8 poses, k1 k2 free
        for k, (i, j) in {"fx": (0, 0), "cx": (0, 2), "cy": (1, 2)}.items():
            assert abs(lens.K[i, j] - truth.K[i, j]) < 4 * sig[k], (name, k)
    assert abs(np.linalg.norm(b.T) - np.linalg.norm(T_CP)) < 4 * b.sigma["baseline_mm"] + 1e-3


def _checker_image(H: np.ndarray, squares: tuple[int, int], square_px: float,
                   size: tuple[int, int], ss: int = 8) -> np.ndarray:
    """A checkerboard (white margin of one square) mapped by the homography H (board px →
    image), integrated over each pixel with ss × ss samples and blurred by 0.5 px."""
    w, h = size
    Hi = np.linalg.inv(H)
    acc = np.zeros((h, w))
    for sy in range(ss):
        for sx in range(ss):
            ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
            q = np.stack([xs + (sx + 0.5) / ss - 0.5, ys + (sy + 0.5) / ss - 0.5,
                          np.ones_like(xs)], -1) @ Hi.T
            i = np.floor(q[..., 0] / q[..., 2] / square_px).astype(int)
            j = np.floor(q[..., 1] / q[..., 2] / square_px).astype(int)
            inside = (i >= 0) & (j >= 0) & (i < squares[0]) & (j < squares[1])
            acc += np.where(inside & ((i + j) % 2 == 0), 0.05, 0.8)
    return cv2.GaussianBlur((acc / ss ** 2 * 3000).astype(np.float32), (0, 0), 0.5)


def test_corner_refinement_reaches_hundredths_of_a_pixel():
    from dotshell.calibration.board import detect

    board = Board("checkerboard", 8, 6, 1.0)
    s = 30.0  # px per square on the print
    a = np.deg2rad(20.0)  # rolled: no edge along the pixel grid
    H = np.array([[np.cos(a), -np.sin(a), 130.0], [np.sin(a), np.cos(a), 40.0],
                  [1.2e-4, -0.8e-4, 1.0]])  # and a perspective tilt
    img = _checker_image(H, (8, 6), s, (400, 340))
    noisy = np.random.default_rng(0).normal(img, np.sqrt(img)).clip(0, 4095).astype(np.uint16)
    det = detect(noisy, board)
    assert det is not None and len(det.ids) == 35
    q = np.column_stack([board.object_points()[:, :2] * s, np.ones(35)]) @ H.T
    truth = q[:, :2] / q[:, 2:]
    err = det.pixels - truth
    if np.abs(err).mean() > 5:  # the checkerboard's 180° ambiguity
        err = det.pixels[::-1] - truth
    rms = float(np.sqrt(np.mean(np.sum(err ** 2, axis=1))))
    assert rms < 0.05, rms


def test_axis_position_is_the_perpendicular_distance():
    from dotshell.calibration.procedure import axis_position_errors
    from dotshell.geometry.calibration import RigCalibration

    d = np.array([0.0, -0.965926, -0.258819])
    truth = RigCalibration(CAM, PROJ, R_CP, T_CP, np.array([0.0, 15.455, 204.141]), d)
    slid = RigCalibration(CAM, PROJ, R_CP, T_CP, truth.axis_point + 0.3 * d, d)
    e = axis_position_errors(slid, truth)
    assert e["axis_point_mm"] < 1e-9 and e["axis_plate_offset_mm"] == pytest.approx(0.3)
    assert e["axis_plate_point_mm"] == pytest.approx(0.3)
    side = RigCalibration(CAM, PROJ, R_CP, T_CP, truth.axis_point + [0.05, 0, 0], d)
    assert axis_position_errors(side, truth)["axis_point_mm"] == pytest.approx(0.05)
    tilted_d = d + [np.deg2rad(0.1), 0, 0]  # 0.1° off: 0.07 mm apart 40 mm up
    tilted = RigCalibration(CAM, PROJ, R_CP, T_CP, truth.axis_point, tilted_d)
    assert axis_position_errors(tilted, truth)["axis_point_mm"] == pytest.approx(
        40 * np.deg2rad(0.1), rel=0.02)
