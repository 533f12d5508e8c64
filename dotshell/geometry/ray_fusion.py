"""Camera–projector and camera–camera points fused along camera 1's rays (pure; mm, pixels).

Two cameras share one *calibrated* projector. For every camera-1 pixel that both cameras
decoded, three devices saw the same surface point: camera 1 (its pixel: exact, a sample
position), the projector (camera 1's decoded column and row) and camera 2 (the sub-pixel position
where it decoded the same code, :func:`dotshell.geometry.code_stereo.match_by_codes`). The point
lies on camera 1's ray ``X = s·r``; each other device contributes two planes through its centre
(constant ideal x and constant ideal y, :func:`device_planes`), each the linear equation
``a s + b = 0`` whose residual divided by the device depth is that device's reprojection error in
ideal normalized coordinates. :func:`solve_along_ray` weights every plane by the inverse variance
of that error and returns the least-squares depth ``s = −Σ w a b / Σ w a²``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DevicePlanes:
    """A device's two planes along N camera-1 rays.

    Attributes:
        a: (N, 2) slopes of the x and y planes along the ray (mm per unit s; ``r`` is unit).
        b: (N, 2) offsets (mm).
        depth_slope: (N,) the device-frame depth along the ray is ``depth_slope·s + depth_offset``.
        depth_offset: scalar (mm).
        focal_px: (2,) the device's focal lengths fx, fy (px): a normalized error times focal
            is the error in the device's pixels.
    """

    a: np.ndarray
    b: np.ndarray
    depth_slope: np.ndarray
    depth_offset: float
    focal_px: np.ndarray


def device_planes(rays1: np.ndarray, R: np.ndarray, T: np.ndarray, ideal: np.ndarray,
                  focal_px: np.ndarray) -> DevicePlanes:
    """Planes of a device at ``X_d = R X1 + T`` (camera 1's frame → the device's, mm) through
    its ideal normalized coordinates ``ideal`` (N, 2) seen along camera-1 unit rays (N, 3)."""
    R = np.asarray(R, float).reshape(3, 3)
    T = np.asarray(T, float).ravel()
    along = rays1 @ R.T                                        # R r per ray: (N, 3)
    a = along[:, :2] - ideal * along[:, 2:3]
    b = T[:2][None, :] - ideal * T[2]
    return DevicePlanes(a, b, along[:, 2], float(T[2]), np.asarray(focal_px, float))


def plane_weights(planes: DevicePlanes, s: np.ndarray, sigma_px: float | np.ndarray
                  ) -> np.ndarray:
    """(N, 2) inverse variances of the planes' residuals (mm⁻²) at depth ``s`` (mm along the
    ray): a residual of ``a s + b`` mm is ``(a s + b)·f / z`` device pixels, so the weight is
    ``(f / (z σ))²`` with σ the device's pixel noise (px)."""
    z = planes.depth_slope * s + planes.depth_offset
    sig = np.broadcast_to(np.asarray(sigma_px, float), z.shape)
    return (planes.focal_px[None, :] / (z * sig)[:, None]) ** 2


def solve_along_ray(planes: list[DevicePlanes], weights: list[np.ndarray]) -> np.ndarray:
    """Least-squares depths s (N,) along the unit rays (mm) from the devices' planes and their
    weights; NaN where the planes leave the depth undetermined."""
    num = sum(np.sum(w * p.a * p.b, axis=1) for p, w in zip(planes, weights))
    den = sum(np.sum(w * p.a ** 2, axis=1) for p, w in zip(planes, weights))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, -num / den, np.nan)


def pixels_per_code(column: np.ndarray, row: np.ndarray, valid: np.ndarray) -> float:
    """How many camera pixels one projector pixel spans in a decoded view (px per projector px):
    the median over interior decoded pixels of ``1 / sqrt|det J|``, J the 2x2 gradient of the
    decoded (column, row) over the image (central differences). NaN when fewer than 10 pixels
    have four decoded neighbours."""
    v = valid
    inner = v[1:-1, 1:-1] & v[1:-1, 2:] & v[1:-1, :-2] & v[2:, 1:-1] & v[:-2, 1:-1]
    if np.count_nonzero(inner) < 10:
        return float("nan")
    dcx = (column[1:-1, 2:] - column[1:-1, :-2])[inner] / 2.0
    dcy = (column[2:, 1:-1] - column[:-2, 1:-1])[inner] / 2.0
    drx = (row[1:-1, 2:] - row[1:-1, :-2])[inner] / 2.0
    dry = (row[2:, 1:-1] - row[:-2, 1:-1])[inner] / 2.0
    det = np.median(np.abs(dcx * dry - dcy * drx))
    return float(1.0 / np.sqrt(det)) if det > 0 else float("nan")


@dataclass
class FusedPoints:
    """Three estimates of the same N matched pixels of camera 1, camera 1's frame (mm).

    Attributes:
        fused: (N, 3) the least-squares points from the projector's and camera 2's planes.
        camera_projector: (N, 3) from the projector's planes alone (camera 1 vs projector).
        camera_camera: (N, 3) from camera 2's planes alone (camera 1 vs camera 2 on ray 1).
        camera2_sigma_px: camera 2's match noise assumed, in projector-code noise units.
        depth_sigma_ratio: median over the points of the predicted depth σ of camera–camera
            over that of camera–projector (> 1: the projector conditions depth better).
    """

    fused: np.ndarray
    camera_projector: np.ndarray
    camera_camera: np.ndarray
    camera2_sigma_px: float
    depth_sigma_ratio: float


def fuse_camera_pair(rays1: np.ndarray, projector_ideal: np.ndarray, camera2_ideal: np.ndarray,
                     to_projector: tuple[np.ndarray, np.ndarray],
                     to_camera2: tuple[np.ndarray, np.ndarray], projector_focal_px: np.ndarray,
                     camera2_focal_px: np.ndarray, camera2_px_per_code: float) -> FusedPoints:
    """Fuse camera 1 – projector and camera 1 – camera 2 along camera 1's unit rays (N, 3).

    The noise model, in units of the decoder's code noise σ (projector px), which cancels:
    camera 1's pixel is exact; the projector's decoded (column, row) at that pixel is off by σ;
    camera 2's matched position is where camera 2 decoded the same code, off by its own code
    noise and camera 1's, both scaled into camera 2's pixels: ``√2 σ·camera2_px_per_code``
    (:func:`pixels_per_code` of camera 2's decoded view). ``to_projector`` / ``to_camera2``:
    (R, T) taking camera 1's frame to the device's (mm)."""
    proj = device_planes(rays1, *to_projector, projector_ideal, projector_focal_px)
    cam2 = device_planes(rays1, *to_camera2, camera2_ideal, camera2_focal_px)
    s0 = solve_along_ray([proj], [np.ones_like(proj.a)])
    sigma2 = float(np.sqrt(2.0) * camera2_px_per_code)
    wp, wc = plane_weights(proj, s0, 1.0), plane_weights(cam2, s0, sigma2)
    s_p = solve_along_ray([proj], [wp])
    s_c = solve_along_ray([cam2], [wc])
    s_f = solve_along_ray([proj, cam2], [wp, wc])
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.sqrt(np.sum(wp * proj.a ** 2, axis=1) / np.sum(wc * cam2.a ** 2, axis=1))
    ratio = ratio[np.isfinite(ratio)]
    return FusedPoints(rays1 * s_f[:, None], rays1 * s_p[:, None], rays1 * s_c[:, None], sigma2,
                       float(np.median(ratio)) if len(ratio) else float("nan"))


def frame_rotation(lens_a, lens_b, grid: int = 16) -> np.ndarray:
    """The rotation Q (3, 3) from the frame of camera calibration ``lens_a`` to that of
    ``lens_b``, two calibrations of one camera: ``X_b = Q X_a`` (the camera centre is both
    frames' origin). Two solves of one camera place its frame a little differently (a principal
    point a pixel off turns the frame by ``1 / f`` rad); Q is the least-squares rotation taking
    ``lens_a``'s rays to ``lens_b``'s over a ``grid``×``grid`` grid of pixels (Kabsch)."""
    xs = np.linspace(0, lens_a.width - 1, grid)
    ys = np.linspace(0, lens_a.height - 1, grid)
    pix = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    ra, rb = lens_a.rays(pix), lens_b.rays(pix)
    u, _, vt = np.linalg.svd(rb.T @ ra)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt
