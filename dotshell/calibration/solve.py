"""Pure calibration solvers (arrays in, dataclasses out; mm, pixels, degrees).

* :func:`calibrate_lens` — intrinsics and distortion of a camera (or a projector seen as an
  inverse camera) from corner correspondences of several poses, leaving out outlier poses.
* :func:`projector_corners` — Moreno & Taubin's local homographies: each target corner's
  projector coordinates from the decoded projector column/row maps around it.
* :func:`calibrate_stereo` — camera–projector pose (and a joint refinement of both lenses).
* :func:`turntable_axis` — the stage's rotation axis from board poses at known stage angles.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares

from dotshell.errors import CalibrationError
from dotshell.geometry.lens import Lens

_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
DISTORTION_FLAGS = {
    "k1": cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "k1k2": cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "k1k2k3": cv2.CALIB_ZERO_TANGENT_DIST,
    "k1k2p1p2": cv2.CALIB_FIX_K3,
    "full": 0,
}


@dataclass
class PoseData:
    """Correspondences of one pose: board points (N, 3) mm and image points (N, 2) px."""

    name: str
    object_points: np.ndarray
    image_points: np.ndarray


@dataclass
class LensSolve:
    """A solved lens with the poses used and left out (name → reason) and errors."""

    lens: Lens
    rms_px: float
    per_pose_rms_px: dict[str, float]
    rvecs: dict[str, np.ndarray]
    tvecs: dict[str, np.ndarray]
    left_out: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class OutlierRule:
    """Poses whose RMS exceeds ``max_rms_px``, or ``factor`` × the median RMS (when that is
    above ``max_rms_px / 4``), are outliers; fewer than ``min_poses`` left is an error."""

    min_poses: int = 6
    factor: float = 3.0
    max_rms_px: float = 1.0

    def outliers(self, rms: dict[str, float]) -> dict[str, str]:
        med = float(np.median(list(rms.values())))
        limit = min(self.max_rms_px, max(self.factor * med, self.max_rms_px / 4))
        return {n: f"reprojection RMS {e:.3f} px > {limit:.3f} px (median {med:.3f} px)"
                for n, e in rms.items() if e > limit}

    def check_count(self, what: str, good: list[str], left_out: dict[str, str]) -> None:
        if len(good) < self.min_poses:
            why = "; ".join(f"{n}: {r}" for n, r in left_out.items()) or "none left out"
            raise CalibrationError(
                f"{what}: only {len(good)} good poses ({', '.join(good) or 'none'}), at least "
                f"{self.min_poses} are needed ([calibrate] min_poses). Left out: {why}. Capture "
                "more poses with the whole target in view, sharp and well exposed.")


def _as_cv(poses: list[PoseData]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    obj = [p.object_points.astype(np.float32).reshape(-1, 1, 3) for p in poses]
    img = [p.image_points.astype(np.float32).reshape(-1, 1, 2) for p in poses]
    return obj, img


def initial_matrix(size: tuple[int, int], poses: list[PoseData]) -> np.ndarray:
    """An initial intrinsic matrix from the planar homographies (OpenCV's initCameraMatrix2D)."""
    obj, img = _as_cv(poses)
    return cv2.initCameraMatrix2D(obj, img, size, 1.0)


def _calibrate_once(poses: list[PoseData], size: tuple[int, int], flags: int,
                    K0: np.ndarray | None) -> tuple[float, np.ndarray, np.ndarray, list, list, np.ndarray]:
    obj, img = _as_cv(poses)
    if K0 is None:
        K0 = initial_matrix(size, poses)
    flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    out = cv2.calibrateCameraExtended(obj, img, size, K0.copy(), np.zeros(5), flags=flags,
                                      criteria=_CRITERIA)
    rms, K, dist, rvecs, tvecs, _, _, per_view = out
    return rms, K, dist.ravel()[:5], list(rvecs), list(tvecs), np.ravel(per_view)


def calibrate_lens(what: str, poses: list[PoseData], size: tuple[int, int], distortion: str,
                   rule: OutlierRule, left_out: dict[str, str] | None = None) -> LensSolve:
    """Intrinsics of ``what`` (``"camera"`` / ``"projector"``) from the poses; outlier poses
    (see :class:`OutlierRule`) are left out one round at a time, worst first."""
    left_out = dict(left_out or {})
    good = [p for p in poses if p.name not in left_out]
    rule.check_count(what, [p.name for p in good], left_out)
    flags = DISTORTION_FLAGS[distortion]
    while True:
        rms, K, dist, rvecs, tvecs, per_view = _calibrate_once(good, size, flags, None)
        per = {p.name: float(e) for p, e in zip(good, per_view)}
        bad = rule.outliers(per)
        if not bad:
            break
        worst = max(bad, key=lambda n: per[n])
        left_out[worst] = bad[worst]
        good = [p for p in good if p.name != worst]
        rule.check_count(what, [p.name for p in good], left_out)
    lens = Lens(K, dist, size[0], size[1])
    return LensSolve(lens, float(rms), per, {p.name: r.ravel() for p, r in zip(good, rvecs)},
                     {p.name: t.ravel() for p, t in zip(good, tvecs)}, left_out)


def projector_corners(corners_px: np.ndarray, column: np.ndarray, row: np.ndarray,
                      valid: np.ndarray, half_window_px: float,
                      min_pixels: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """Projector coordinates of target corners by local homographies (Moreno & Taubin 2012).

    For each camera corner, the decoded pixels within ``half_window_px`` (a square window)
    give a least-squares homography camera → projector, which maps the corner itself.

    Returns:
        (projector pixels (N, 2), ok (N,) bool — enough decoded pixels and a finite result).
    """
    h, w = valid.shape
    out = np.full((len(corners_px), 2), np.nan)
    ok = np.zeros(len(corners_px), bool)
    r = int(np.ceil(half_window_px))
    for k, (x, y) in enumerate(corners_px):
        x0, x1 = max(0, int(round(x)) - r), min(w, int(round(x)) + r + 1)
        y0, y1 = max(0, int(round(y)) - r), min(h, int(round(y)) + r + 1)
        if x1 <= x0 or y1 <= y0:
            continue
        v = valid[y0:y1, x0:x1]
        if v.sum() < min_pixels:
            continue
        ys, xs = np.nonzero(v)
        src = np.column_stack([xs + x0, ys + y0]).astype(np.float64)
        dst = np.column_stack([column[y0:y1, x0:x1][v], row[y0:y1, x0:x1][v]]).astype(np.float64)
        # centre and scale for conditioning, then a least-squares homography
        H, _ = cv2.findHomography(src - (x, y), dst, 0)
        if H is None:
            continue
        p = H @ np.array([0.0, 0.0, 1.0])
        if abs(p[2]) < 1e-12:
            continue
        out[k] = p[:2] / p[2]
        ok[k] = np.isfinite(out[k]).all()
    return out, ok


@dataclass
class StereoSolve:
    """Camera–projector solve: both lenses refined jointly, the pose and per-pose errors."""

    camera: Lens
    projector: Lens
    R: np.ndarray
    T: np.ndarray
    rms_px: float
    per_pose_rms_px: dict[str, float]


def calibrate_stereo(cam: LensSolve, proj: LensSolve, cam_poses: list[PoseData],
                     proj_poses: list[PoseData], distortion: str | tuple[str, str]) -> StereoSolve:
    """Jointly refine the camera and projector lenses and solve ``X_p = R X_c + T`` from the
    poses both solves kept (each with the corners seen by both). With two different models
    (camera model, projector model) the lenses stay as their own solves left them (the bundle
    adjustment refines them) and only the pose is solved."""
    names = [n for n in proj.per_pose_rms_px if n in cam.per_pose_rms_px]
    if not names:
        raise CalibrationError("camera–projector: no pose was kept by both the camera and the "
                               "projector solve.")
    cam_by = {p.name: p for p in cam_poses}
    proj_by = {p.name: p for p in proj_poses}
    obj, ic, ip = [], [], []
    for n in names:
        # projector poses carry a subset of the camera corners: match by object point
        c, p = cam_by[n], proj_by[n]
        key = {tuple(np.round(o, 6)): i for i, o in enumerate(c.object_points)}
        idx = np.array([key[tuple(np.round(o, 6))] for o in p.object_points])
        obj.append(p.object_points.astype(np.float32).reshape(-1, 1, 3))
        ic.append(c.image_points[idx].astype(np.float32).reshape(-1, 1, 2))
        ip.append(p.image_points.astype(np.float32).reshape(-1, 1, 2))
    models = (distortion, distortion) if isinstance(distortion, str) else tuple(distortion)
    flags = (DISTORTION_FLAGS[models[0]] | cv2.CALIB_USE_INTRINSIC_GUESS
             if models[0] == models[1] else cv2.CALIB_FIX_INTRINSIC)
    out = cv2.stereoCalibrateExtended(
        obj, ic, ip, cam.lens.K.copy(), cam.lens.dist.copy(), proj.lens.K.copy(),
        proj.lens.dist.copy(), cam.lens.size, np.eye(3), np.zeros(3), flags=flags,
        criteria=_CRITERIA)
    rms, K1, D1, K2, D2, R, T = out[:7]
    per_view = np.asarray(out[11]).reshape(len(names), -1)
    per = {n: float(np.sqrt(np.mean(np.square(e)))) for n, e in zip(names, per_view)}
    camera = Lens(K1, D1.ravel()[:5], *cam.lens.size)
    projector = Lens(K2, D2.ravel()[:5], *proj.lens.size)
    return StereoSolve(camera, projector, np.asarray(R), np.asarray(T).ravel(), float(rms), per)


@dataclass
class AxisSolve:
    """Turntable axis in the camera frame: ``point`` at the stage plate (mm), unit
    ``direction`` (plate → sample), and the RMS reprojection error of the joint fit (px)."""

    point: np.ndarray
    direction: np.ndarray
    rms_px: float
    per_pose_rms_px: dict[str, float]


def _axis_rotation(direction: np.ndarray, degrees: float) -> np.ndarray:
    rvec = np.asarray(direction, float) / np.linalg.norm(direction) * np.deg2rad(degrees)
    return cv2.Rodrigues(rvec)[0]


def _initial_axis(R: list[np.ndarray], t: list[np.ndarray], angles: np.ndarray):
    """Axis from the relative motions between the pose nearest 0° and every other pose."""
    ref = int(np.argmin(np.abs(angles)))
    dirs, A, b = [], [], []
    for k in range(len(angles)):
        dt = angles[k] - angles[ref]
        if k == ref or abs(dt) < 1e-6:
            continue
        Rr = R[k] @ R[ref].T
        tr = t[k] - Rr @ t[ref]
        rvec = cv2.Rodrigues(Rr)[0].ravel()
        dirs.append(rvec / np.deg2rad(dt))
        A.append(np.eye(3) - Rr)
        b.append(tr)
    d = np.mean(dirs, axis=0)
    d /= np.linalg.norm(d)
    p = np.linalg.lstsq(np.vstack(A), np.concatenate(b), rcond=None)[0]
    return d, p - d * (p @ d)


def turntable_axis(camera: Lens, board_points: np.ndarray, detections: list[tuple[str, float, np.ndarray, np.ndarray]],
                   board_centre: np.ndarray, centre_height_mm: float) -> AxisSolve:
    """The rotation axis of the stage from one board pose seen at several stage angles.

    Args:
        camera: calibrated camera.
        board_points: (N, 3) board corners by id (mm, board frame).
        detections: (pose name, stage angle in degrees, corner ids (M,), pixels (M, 2)).
        board_centre: the board's centre in the board frame (mm).
        centre_height_mm: height of the board centre above the stage plate, along the axis.

    Solved jointly: the board pose at 0° (6 parameters) and the axis (4), so that the board
    turned by each stage angle about the axis reprojects onto its detected corners.
    """
    angles = np.array([a for _, a, _, _ in detections], float)
    if np.ptp(angles) < 20.0:
        raise CalibrationError(f"turntable: the stage angles {angles.tolist()} span less than "
                               "20°; list angles at least 20° apart in [calibrate] "
                               "turntable_angles_deg.")
    R, t = [], []
    for name, _, ids, px in detections:
        ok, rvec, tvec = cv2.solvePnP(board_points[ids], px, camera.K, camera.dist,
                                      flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            raise CalibrationError(f"turntable: the board pose of {name} could not be solved.")
        R.append(cv2.Rodrigues(rvec)[0])
        t.append(tvec.ravel())
    d0, p0 = _initial_axis(R, t, angles)
    # board pose at 0°: undo each pose's rotation about the initial axis and average
    Rb = [_axis_rotation(d0, -a) for a in angles]
    M0 = [Rb[k] @ R[k] for k in range(len(R))]
    t0 = np.mean([Rb[k] @ (t[k] - p0) + p0 for k in range(len(R))], axis=0)
    r0 = cv2.Rodrigues(M0[int(np.argmin(np.abs(angles)))])[0].ravel()
    # axis parametrised by two angles of its direction and a 2-D offset across it
    e1 = np.cross(d0, [1.0, 0, 0] if abs(d0[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d0, e1)

    def unpack(x):
        d = d0 + x[6] * e1 + x[7] * e2
        d /= np.linalg.norm(d)
        p = p0 + x[8] * e1 + x[9] * e2
        return x[:3], x[3:6], d, p

    def residuals(x):
        rv, tv, d, p = unpack(x)
        Rz = cv2.Rodrigues(rv)[0]
        res = []
        for _, a, ids, px in detections:
            Ra = _axis_rotation(d, a)
            Rk = Ra @ Rz
            tk = Ra @ (tv - p) + p
            proj, _ = cv2.projectPoints(board_points[ids], cv2.Rodrigues(Rk)[0], tk, camera.K,
                                        camera.dist)
            res.append((proj.reshape(-1, 2) - px).ravel())
        return np.concatenate(res)

    x0 = np.concatenate([r0, t0, np.zeros(4)])
    sol = least_squares(residuals, x0, method="lm", x_scale="jac")
    rv, tv, d, p = unpack(sol.x)
    res = residuals(sol.x)
    per, start = {}, 0
    for name, _, ids, _ in detections:
        n = 2 * len(ids)
        per[name] = float(np.sqrt(np.mean(res[start:start + n] ** 2) * 2))
        start += n
    # the plate point: the board centre's foot on the axis, lowered by its height
    centre = cv2.Rodrigues(rv)[0] @ board_centre + tv
    foot = p + d * ((centre - p) @ d)
    point = foot - d * centre_height_mm
    return AxisSolve(point, d, float(np.sqrt(np.mean(res ** 2) * 2)), per)
