import numpy as np
import pytest

from dotshell.geometry.calibration import RigCalibration, rot_z
from dotshell.geometry.fit import fit_cylinder
from dotshell.geometry.lens import lens_from_fov
from dotshell.geometry.triangulate import triangulate


def _rig(dist=(-0.08, 0.04, 0.0, 0.0, 0.0), pdist=(0.05, 0.0, 0.0, 0.0, 0.0)):
    cam = lens_from_fov(640, 512, 2000.0, dist)
    prj = lens_from_fov(512, 384, 1300.0, pdist)
    a = np.deg2rad(-22.0)  # projector turned about the camera's y axis
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    C = np.array([75.0, 0.0, 10.0])  # projector centre in camera frame (mm)
    return RigCalibration(cam, prj, R, -R @ C, axis_point=[0, 15, 200], axis_direction=[0, -1, 0])


def test_stage_frame_roundtrip_and_rotation_sense():
    cal = _rig()
    p = np.array([[7.7, 0.0, 10.0], [0.0, 7.7, 3.0]])
    for ang in (0.0, 30.0, 275.0):
        assert np.allclose(cal.camera_to_sample(cal.sample_to_camera(p, ang), ang), p)
    # stage at 90°: the sample's +x point appears on the stage frame's +y side
    cam = cal.sample_to_camera(p[:1], 90.0)
    aligned = (cam - cal.axis_point) @ cal.stage_basis().T
    assert np.allclose(aligned, [[0.0, 7.7, 10.0]], atol=1e-9)
    # stage x axis points towards the camera
    assert cal.stage_basis()[0] @ -cal.axis_point > 0


@pytest.mark.parametrize("use_rows", [True, False])
def test_triangulation_recovers_points_through_both_lens_distortions(use_rows):
    cal = _rig()
    rng = np.random.default_rng(3)
    X = rng.uniform([-15, -15, 185], [15, 15, 215], size=(500, 3))
    cam_px = cal.camera.project(X)
    prj_px = cal.projector.project(X @ cal.R.T + cal.T)
    tri = triangulate(cal.camera.rays(cam_px), prj_px[:, 0], cal,
                      row=prj_px[:, 1] if use_rows else None)
    assert tri.keep.all()
    assert np.abs(tri.points - X).max() < 1e-6


def test_row_consistency_rejects_wrong_rows():
    cal = _rig()
    X = np.array([[0.0, 0.0, 200.0], [5.0, 5.0, 205.0]])
    cam_px = cal.camera.project(X)
    prj_px = cal.projector.project(X @ cal.R.T + cal.T)
    rows = prj_px[:, 1] + np.array([0.5, 6.0])
    tri = triangulate(cal.camera.rays(cam_px), prj_px[:, 0], cal, row=rows, row_tolerance_px=1.5)
    assert tri.keep.tolist() == [True, False] and tri.row_rejected.tolist() == [False, True]


def _looking_at(C: np.ndarray, target=(0.0, 0.0, 200.0), up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """Rotation camera frame → projector frame of a projector at C looking at ``target``."""
    z = np.asarray(target) - C
    z /= np.linalg.norm(z)
    x = np.cross(-np.asarray(up), z)
    x /= np.linalg.norm(x)
    return np.vstack([x, np.cross(z, x), z])


@pytest.mark.parametrize("centre", [(80.0, -4.0, 6.0), (0.0, -80.0, 6.0), (57.0, -57.0, 6.0)],
                         ids=["beside", "above", "diagonal"])
def test_both_codes_triangulate_any_baseline_direction(centre):
    """Projector beside, above or diagonal to the camera: the least-squares point from column
    and row planes is exact on clean data and as good as the beside rig with 0.05 px noise;
    columns alone graze when the projector is above."""
    cam = lens_from_fov(640, 512, 2000.0, (-0.08, 0.04, 0, 0, 0))
    prj = lens_from_fov(512, 384, 1300.0, (0.05, 0, 0, 0, 0))
    C = np.asarray(centre)
    R = _looking_at(C)
    cal = RigCalibration(cam, prj, R, -R @ C, axis_point=[0, 15, 200], axis_direction=[0, -1, 0])
    rng = np.random.default_rng(5)
    X = rng.uniform([-12, -12, 190], [12, 12, 210], size=(2000, 3))
    cam_px = cam.project(X)
    prj_px = prj.project(X @ R.T + cal.T)
    tri = triangulate(cam.rays(cam_px), prj_px[:, 0], cal, row=prj_px[:, 1])
    assert tri.keep.all() and np.abs(tri.points - X).max() < 1e-6
    noisy = prj_px + rng.normal(scale=0.05, size=prj_px.shape)
    tri = triangulate(cam.rays(cam_px), noisy[:, 0], cal, row=noisy[:, 1])
    depth_rms = np.sqrt(np.mean(np.sum((tri.points - X) ** 2, axis=1)))
    # one plane at the ~22° triangulation angle: 0.05 px ≈ 8 µm along the plane's normal
    # → ~20 µm along the ray; the diagonal rig uses both planes and does no worse
    assert depth_rms < 0.025
    cols_only = triangulate(cam.rays(cam_px), prj_px[:, 0], cal)
    if centre[0] == 0.0:
        assert cols_only.grazing.all() and not cols_only.keep.any()
    else:
        assert cols_only.keep.all()


def test_cylinder_fit_recovers_radius_and_axis():
    rng = np.random.default_rng(0)
    t = rng.uniform(0, 2 * np.pi, 3000)
    z = rng.uniform(0, 30, 3000)
    pts = np.column_stack([7.7 * np.cos(t), 7.7 * np.sin(t), z])
    tilt = rot_z(0)  # identity; then tilt by 2° about x and shift
    a = np.deg2rad(2.0)
    Rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    pts = pts @ (Rx @ tilt).T + [0.3, -0.2, 0]
    pts += rng.normal(scale=0.01, size=pts.shape)
    fit = fit_cylinder(pts)
    assert abs(fit.radius_mm - 7.7) < 0.002
    assert np.degrees(np.arccos(abs(fit.axis[2]))) == pytest.approx(2.0, abs=0.02)
    assert fit.rms_mm == pytest.approx(0.01, rel=0.15)  # radial share of isotropic noise


def test_calibration_json_roundtrip_and_errors(tmp_path):
    from dotshell.errors import CalibrationError

    cal = _rig()
    cal.save(tmp_path / "c.json")
    back = RigCalibration.load(tmp_path / "c.json")
    assert np.allclose(back.R, cal.R) and np.allclose(back.camera.dist, cal.camera.dist)
    assert back.baseline_mm == pytest.approx(cal.baseline_mm)
    (tmp_path / "bad.json").write_text('{"format": "dotshell-calibration/1", "camera": {}}')
    with pytest.raises(CalibrationError, match="bad.json: calibration is incomplete"):
        RigCalibration.load(tmp_path / "bad.json")
    with pytest.raises(CalibrationError, match="does not exist"):
        RigCalibration.load(tmp_path / "nope.json")


@pytest.mark.parametrize("pdist", [(0.05, 0.0, 0.0, 0.0, 0.0), (-0.5, 0.1, 0.02, -0.02, 0.0)],
                         ids=["mild", "strong"])
@pytest.mark.parametrize("threads", [1, 2])
def test_image_triangulation_equals_per_point_and_the_truth(pdist, threads):
    """``triangulate_image`` (row batches, undistortion vectorized over a row, continued to
    convergence where a strongly distorting projector needs more steps) gives what
    ``triangulate`` gives per point, and the true surface; on two threads its bands count
    their flags apart."""
    from dotshell.runtime import parallel
    from dotshell.geometry import triangulate as tr

    cam = lens_from_fov(320, 256, 1000.0, (-0.08, 0.04, 0, 0, 0))
    lens_p = lens_from_fov(512, 384, 500.0, pdist)
    C = np.array([80.0, -4.0, 6.0])
    R = _looking_at(C)
    cal = RigCalibration(cam, lens_p, R, -R @ C, axis_point=[0, 15, 200], axis_direction=[0, -1, 0])
    rays = tr.camera_ray_grid(cal.camera)
    h, w = rays.shape[:2]
    # a tilted plane z = 200 + 0.1 x (mm) seen by every camera pixel
    s = 200.0 / (rays[..., 2] - 0.1 * rays[..., 0])
    X = rays * s[..., None]
    prj = cal.projector.project(X.reshape(-1, 3) @ cal.R.T + cal.T).reshape(h, w, 2)
    rng = np.random.default_rng(5)
    valid = (rng.random((h, w)) > 0.3) & (prj[..., 0] > 0) & (prj[..., 0] < 512)
    assert valid.mean() > 0.5
    row = prj[..., 1].astype(np.float32)
    row[::7, ::5] += 4.0  # rows off the epipolar line: rejected
    column = prj[..., 0].astype(np.float32)
    to_frame = np.column_stack([rot_z(30.0), [1.0, -2.0, 3.0]])
    with parallel.threads(threads):
        img = tr.triangulate_image(valid, column, row, cal, row_tolerance_px=1.5,
                                   to_frame=to_frame)
        columns_only = tr.solve_image(valid, column, None, cal, min_ray_angle_deg=2.0,
                                      depth_image=True)
        both = tr.solve_image(valid, column, row, cal, row_tolerance_px=1.5, depth_image=True)
    for sol in (columns_only, both):  # the kept points' depths where they are, 0 elsewhere
        want = np.zeros((h, w), np.float32)
        want[sol.pixels[sol.kept, 1], sol.pixels[sol.kept, 0]] = sol.depth[sol.kept]
        assert np.array_equal(sol.depth_image, want) and (want > 0).sum() > h * w // 3
    assert img.counts == both.counts
    ys, xs = np.nonzero(valid)
    per_point = triangulate(rays[ys, xs], column[ys, xs], cal, row=row[ys, xs],
                            row_tolerance_px=1.5)
    per_column = triangulate(rays[ys, xs], column[ys, xs], cal, min_ray_angle_deg=2.0)
    assert np.array_equal(columns_only.kept, per_column.keep)
    assert columns_only.counts == {"triangulated": np.count_nonzero(per_column.keep),
                                   "row_rejected": 0,
                                   "grazing": np.count_nonzero(per_column.grazing)}
    assert columns_only.counts["triangulated"] > len(ys) // 2
    kept = per_point.keep
    assert 0 < np.count_nonzero(~kept) < len(kept) // 5
    assert img.counts["triangulated"] == np.count_nonzero(kept)
    assert img.counts["row_rejected"] == np.count_nonzero(per_point.row_rejected)
    assert np.array_equal(img.pixels, np.column_stack([xs, ys])[kept])
    moved = per_point.points[kept] @ to_frame[:, :3].T + to_frame[:, 3]
    assert np.abs(img.points - moved).max() < 1e-10
    assert np.abs(img.depth - per_point.points[kept, 2]).max() < 1e-10
    # how many undistortion steps the pixels need: the strong lens needs more than a row
    # batch takes for all (the rest continue alone), the mild one fewer
    k = lens_p.K
    x0 = (column[ys, xs].astype(float) - k[0, 2]) / k[0, 0]
    y0 = (row[ys, xs].astype(float) - k[1, 2]) / k[1, 1]
    x, y, steps = x0, y0, np.zeros(len(x0), int)
    for _ in range(50):
        nx, ny = tr._undistort_step(tr._twelve_terms(lens_p.dist), x0, y0, x, y)
        moving = (np.abs(nx - x) >= 1e-15) | (np.abs(ny - y) >= 1e-15)
        steps += moving
        x, y = nx, ny
    assert (steps.max() > tr.BATCH_UNDISTORT_STEPS) == (pdist[0] < 0)
    truth = X[ys, xs][kept] @ to_frame[:, :3].T + to_frame[:, 3]
    # float32 decoded coordinates: ~1e-5 px, a few µm along these rays
    assert np.abs(img.points - truth).max() < 0.01


# ---- OpenCV's longer distortion models (issue 33) ----------------------------------------------

RATIONAL = (-0.08, 0.04, 0.001, -0.0005, 0.0, 0.02, -0.01, 0.005)  # k1..k3, k4..k6
THIN_PRISM = RATIONAL + (0.002, -0.001, 0.0015, 0.0005)  # + s1..s4


@pytest.mark.parametrize("dist", [RATIONAL, THIN_PRISM, THIN_PRISM + (0.0, 0.0)],
                         ids=["rational", "thin prism", "14 terms, not tilted"])
def test_every_opencv_distortion_model_is_applied_as_opencv_applies_it(dist):
    """Issue 33: an 8-term rational calibration was cut to 5 terms without a word, moving a
    corner pixel by ~19 px. Projection equals cv2.projectPoints; triangulation through the
    model recovers the points; the same rig cut to 5 terms does not."""
    import cv2

    from dotshell.geometry.lens import Lens

    cal = _rig(dist=dist, pdist=dist)
    assert cal.camera.dist.size == 12
    rng = np.random.default_rng(5)
    X = rng.uniform([-40, -30, 185], [40, 30, 215], size=(400, 3))
    ours = cal.camera.project(X)
    theirs, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), cal.camera.K, np.array(dist))
    assert np.abs(ours - theirs.reshape(-1, 2)).max() < 1e-9
    prj_px = cal.projector.project(X @ cal.R.T + cal.T)
    tri = triangulate(cal.camera.rays(ours), prj_px[:, 0], cal, row=prj_px[:, 1])
    assert tri.keep.all() and np.abs(tri.points - X).max() < 1e-6
    cut = RigCalibration(Lens(cal.camera.K, dist[:5], 640, 512),
                         Lens(cal.projector.K, dist[:5], 512, 384), cal.R, cal.T,
                         cal.axis_point, cal.axis_direction)
    wrong = triangulate(cut.camera.rays(ours), prj_px[:, 0], cut)
    assert np.nanmax(np.abs(wrong.points - X[wrong.keep])) > 0.05  # mm: the terms matter


@pytest.mark.parametrize("dist, says", [
    ((0.1,) * 40, "40 distortion terms: OpenCV's models have 4, 5, 8, 12 or 14"),
    ((0.0,) * 12 + (0.01, 0.0), "tilted-sensor distortion (tau_x = 0.01, tau_y = 0)"),
])
def test_distortion_models_nothing_applies_are_refused_naming_the_terms(dist, says):
    from dotshell.geometry.lens import Lens

    with pytest.raises(ValueError) as refused:
        Lens(np.eye(3), dist, 64, 48)
    assert says in str(refused.value)


def test_opencv_file_with_a_rational_model_reads_back_whole(tmp_path):
    from dotshell.geometry.opencv_io import read_opencv_calibration, write_opencv_calibration

    cal = _rig(dist=THIN_PRISM, pdist=RATIONAL)
    back = read_opencv_calibration(write_opencv_calibration(cal, tmp_path / "cal.yml"))
    assert np.array_equal(back.camera.dist, cal.camera.dist)
    assert np.array_equal(back.projector.dist[:8], RATIONAL)


def test_camera_ideal_grid_is_the_ray_grid_without_its_constant_third_component():
    """The image solves read the (H, W, 2) grid of ideal camera coordinates; the (H, W, 3) rays
    are that grid with z = 1, value for value."""
    from dotshell.geometry import triangulate as tr

    cam = lens_from_fov(96, 64, 300.0, (-0.08, 0.04, 0.0, 0.0, 0.0))
    xy, rays = tr.camera_ideal_grid(cam), tr.camera_ray_grid(cam)
    assert xy.shape == (64, 96, 2) and xy.flags.c_contiguous
    assert np.array_equal(rays[..., :2], xy) and np.all(rays[..., 2] == 1.0)
    ys, xs = np.mgrid[0:64, 0:96]
    px = np.column_stack([xs.ravel(), ys.ravel()]).astype(float)
    assert np.array_equal(xy.reshape(-1, 2), cam.undistort(px))
