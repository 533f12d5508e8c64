"""Joint bundle adjustment of a camera–projector pair on a planar target (pure; mm, pixels).

One least-squares problem holds everything the free poses measure: both lenses (focal lengths,
principal points, the distortion terms solved for), the camera → projector pose and the board
pose of every view. Each board corner contributes its camera residual and, where the gray code
decoded it, its projector residual. Because the projector sees the *same* board poses from
another direction, the principal points are constrained by both views at once (a principal
point shift of one device is no longer absorbed by turning the poses alone).

The parameter covariance ``s² (JᵀJ)⁻¹`` (``s²`` the residual variance) gives each intrinsic
its one-sigma uncertainty, reported with the result.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares

from dotshell.calibration.solve import PoseData
from dotshell.errors import CalibrationError
from dotshell.geometry.lens import Lens, project_points

#: Distortion coefficients (OpenCV order k1, k2, p1, p2, k3) solved for, per ``distortion``.
FREE_DISTORTION = {"k1": (0,), "k1k2": (0, 1), "k1k2k3": (0, 1, 4), "k1k2p1p2": (0, 1, 2, 3),
                   "full": (0, 1, 2, 3, 4)}
INTRINSIC_NAMES = ("fx", "fy", "cx", "cy")
DISTORTION_NAMES = ("k1", "k2", "p1", "p2", "k3")


@dataclass
class _Layout:
    """Where each group of parameters sits in the parameter vector."""

    n_dist_cam: int
    n_dist_proj: int
    n_poses: int

    @property
    def lenses_len(self) -> int:
        return 8 + self.n_dist_cam + self.n_dist_proj

    @property
    def cam(self) -> slice:
        return slice(0, 4 + self.n_dist_cam)

    @property
    def proj(self) -> slice:
        return slice(4 + self.n_dist_cam, self.lenses_len)

    @property
    def stereo(self) -> slice:
        return slice(self.lenses_len, self.lenses_len + 6)

    def pose(self, i: int) -> slice:
        s = self.lenses_len + 6 + 6 * i
        return slice(s, s + 6)

    @property
    def size(self) -> int:
        return self.lenses_len + 6 + 6 * self.n_poses


@dataclass
class BundleSolve:
    """Result of :func:`bundle_adjust`.

    ``sigma`` holds the one-sigma uncertainties from the covariance: ``camera`` and
    ``projector`` → {fx, fy, cx, cy (px), and each distortion term solved}, ``baseline_mm``.
    ``residuals`` holds, per pose name, ``camera`` and ``projector`` → (corner pixels (N, 2),
    residual vectors (N, 2) px, model minus measured).
    """

    camera: Lens
    projector: Lens
    R: np.ndarray
    T: np.ndarray
    rvecs: dict[str, np.ndarray]
    tvecs: dict[str, np.ndarray]
    rms_px: float
    camera_rms_px: float
    projector_rms_px: float
    per_pose_rms_px: dict[str, float]
    sigma: dict
    residuals: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]] = field(default_factory=dict)


def _lens_vector(lens: Lens, free: tuple[int, ...]) -> np.ndarray:
    K = lens.K
    return np.concatenate([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], np.asarray(lens.dist)[list(free)]])


def _lens_from(v: np.ndarray, free: tuple[int, ...], fixed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    K = np.array([[v[0], 0.0, v[2]], [0.0, v[1], v[3]], [0.0, 0.0, 1.0]])
    dist = np.array(fixed, float)
    dist[list(free)] = v[4:]
    return K, dist


def bundle_adjust(cam_poses: list[PoseData], proj_poses: list[PoseData], camera: Lens,
                  projector: Lens, R: np.ndarray, T: np.ndarray, rvecs: dict[str, np.ndarray],
                  tvecs: dict[str, np.ndarray], distortion: str | tuple[str, str]) -> BundleSolve:
    """Refine both lenses, ``X_p = R X_c + T`` and every board pose together.

    Args:
        cam_poses, proj_poses: camera and projector corners per pose (projector poses may be
            missing or carry a subset of the corners; matched by pose name and object point).
        camera, projector, R, T: the initial solve (e.g. OpenCV's stereo calibration).
        rvecs, tvecs: initial board → camera poses by pose name (Rodrigues vector, mm).
        distortion: a model of :data:`FREE_DISTORTION` for both lenses, or (camera model,
            projector model); terms not solved stay as given.
    """
    problem = _Problem(cam_poses, proj_poses, camera, projector, R, T, rvecs, tvecs, distortion)
    # Levenberg–Marquardt from the stereo solve converges in a few steps (a dense Jacobian of
    # ~150 parameters is cheap); the sparse trust-region variant crawled for hundreds
    sol = least_squares(problem.residuals, problem.x0, method="lm", x_scale="jac",
                        xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=100 * len(problem.x0))
    return problem.result(sol)


class _Problem:
    """The bundle-adjustment problem: parameter layout, start vector and residuals."""

    def __init__(self, cam_poses: list[PoseData], proj_poses: list[PoseData], camera: Lens,
                 projector: Lens, R: np.ndarray, T: np.ndarray, rvecs: dict[str, np.ndarray],
                 tvecs: dict[str, np.ndarray], distortion: str | tuple[str, str]) -> None:
        cam_model, proj_model = (distortion, distortion) if isinstance(distortion, str) else distortion
        self.free_c, self.free_p = FREE_DISTORTION[cam_model], FREE_DISTORTION[proj_model]
        self.names = [p.name for p in cam_poses if p.name in rvecs]
        if len(self.names) < 3:
            raise CalibrationError(f"bundle adjustment: {len(self.names)} poses with a board "
                                   "pose, at least 3 are needed.")
        cam_by = {p.name: p for p in cam_poses}
        proj_by = {p.name: p for p in proj_poses}
        self.camera, self.projector = camera, projector
        self.lay = lay = _Layout(len(self.free_c), len(self.free_p), len(self.names))
        x0 = np.zeros(lay.size)
        x0[lay.cam] = _lens_vector(camera, self.free_c)
        x0[lay.proj] = _lens_vector(projector, self.free_p)
        x0[lay.stereo] = np.concatenate([cv2.Rodrigues(np.asarray(R, float))[0].ravel(),
                                         np.asarray(T, float).ravel()])
        for i, n in enumerate(self.names):
            x0[lay.pose(i)] = np.concatenate([np.ravel(rvecs[n]), np.ravel(tvecs[n])])
        self.x0 = x0
        none3, none2 = np.zeros((0, 3)), np.zeros((0, 2))
        self.obj_c = [cam_by[n].object_points for n in self.names]
        self.img_c = [cam_by[n].image_points for n in self.names]
        self.obj_p = [proj_by[n].object_points if n in proj_by else none3 for n in self.names]
        self.img_p = [proj_by[n].image_points if n in proj_by else none2 for n in self.names]
        self.dist_c0 = np.asarray(camera.dist, float)
        self.dist_p0 = np.asarray(projector.dist, float)
        self.n_cam = [len(o) for o in self.obj_c]
        self.n_proj = [len(o) for o in self.obj_p]

    def lenses(self, x: np.ndarray):
        Kc, dc = _lens_from(x[self.lay.cam], self.free_c, self.dist_c0)
        Kp, dp = _lens_from(x[self.lay.proj], self.free_p, self.dist_p0)
        return Kc, dc, Kp, dp

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """Camera then projector residuals (px) of each pose in turn."""
        lay = self.lay
        Kc, dc, Kp, dp = self.lenses(x)
        Rs = cv2.Rodrigues(x[lay.stereo][:3])[0]
        Ts = x[lay.stereo][3:]
        out = []
        for i in range(len(self.names)):
            pv = x[lay.pose(i)]
            Rb = cv2.Rodrigues(pv[:3])[0]
            out.append((project_points(Kc, dc, self.obj_c[i] @ Rb.T + pv[3:]) - self.img_c[i]).ravel())
            if self.n_proj[i]:
                Xc = self.obj_p[i] @ Rb.T + pv[3:]
                out.append((project_points(Kp, dp, Xc @ Rs.T + Ts) - self.img_p[i]).ravel())
        return np.concatenate(out)

    def result(self, sol) -> BundleSolve:
        """The solved lenses, poses and RMS errors (px) of ``sol``, with one-sigma values."""
        x, lay, names = sol.x, self.lay, self.names
        Kc, dc, Kp, dp = self.lenses(x)
        res = sol.fun
        per, cam_sq, proj_sq, r, vectors = {}, [], [], 0, {}
        for i, (n, nc, np_) in enumerate(zip(names, self.n_cam, self.n_proj)):
            c = res[r:r + 2 * nc]
            p = res[r + 2 * nc:r + 2 * nc + 2 * np_]
            r += 2 * (nc + np_)
            vectors[n] = {"camera": (self.img_c[i], c.reshape(-1, 2)),
                          "projector": (self.img_p[i], p.reshape(-1, 2))}
            cam_sq.append(c ** 2)
            proj_sq.append(p ** 2)
            both = np.concatenate([c, p])
            per[n] = float(np.sqrt(2 * np.mean(both ** 2)))
        cam_all, proj_all = np.concatenate(cam_sq), np.concatenate(proj_sq)
        Rs = cv2.Rodrigues(x[lay.stereo][:3])[0]
        return BundleSolve(
            Lens(Kc, dc, *self.camera.size), Lens(Kp, dp, *self.projector.size), Rs,
            x[lay.stereo][3:].copy(),
            {n: x[lay.pose(i)][:3].copy() for i, n in enumerate(names)},
            {n: x[lay.pose(i)][3:].copy() for i, n in enumerate(names)},
            float(np.sqrt(2 * np.mean(res ** 2))), float(np.sqrt(2 * np.mean(cam_all))),
            float(np.sqrt(2 * np.mean(proj_all))) if len(proj_all) else float("nan"), per,
            _sigmas(sol, lay, self.free_c, self.free_p), vectors)


def covariance(jac, residuals: np.ndarray) -> np.ndarray:
    """``s² (JᵀJ)⁻¹`` with ``s²`` the residual variance per degree of freedom. The columns are
    equilibrated first (focal lengths in thousands of pixels next to rotations in radians), so
    the weak directions are inverted, not truncated."""
    J = jac.toarray() if hasattr(jac, "toarray") else np.asarray(jac, float)
    dof = max(1, len(residuals) - J.shape[1])
    s2 = float(residuals @ residuals) / dof
    scale = np.linalg.norm(J, axis=0)
    scale[scale == 0] = 1.0
    Js = J / scale
    inv = np.linalg.inv(Js.T @ Js)
    return s2 * inv / np.outer(scale, scale)


def _sigmas(sol, lay: _Layout, free_c: tuple[int, ...], free_p: tuple[int, ...]) -> dict:
    cov = covariance(sol.jac, sol.fun)
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    out: dict = {}
    for which, part, free in (("camera", lay.cam, free_c), ("projector", lay.proj, free_p)):
        names = INTRINSIC_NAMES + tuple(DISTORTION_NAMES[i] for i in free)
        out[which] = dict(zip(names, sd[part].tolist()))
    T = sol.x[lay.stereo][3:]
    g = T / np.linalg.norm(T)  # d|T|/dT
    cT = cov[lay.stereo, lay.stereo][3:, 3:]
    out["baseline_mm"] = float(np.sqrt(g @ cT @ g))
    return out
