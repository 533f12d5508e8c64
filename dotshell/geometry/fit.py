"""Shape fits for validation: radius about a known axis, and a free least-squares cylinder."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares


@dataclass(frozen=True)
class CylinderFit:
    """A least-squares cylinder (mm). ``axis`` is a unit vector, ``point`` the axis point
    closest to the cloud's centroid; ``rms_mm`` the RMS of the radial residuals."""

    point: np.ndarray
    axis: np.ndarray
    radius_mm: float
    rms_mm: float


def radial_distance(points: np.ndarray, point: np.ndarray, axis: np.ndarray,
                    work: np.ndarray | None = None) -> np.ndarray:
    """Distance (mm) of each point (N, 3) from the line through ``point`` along ``axis``.
    ``work``: an (N, 3) float64 scratch array to compute in (a fit calls this ~25 times; a
    fresh 5 MB array each time costs more in page faults than the arithmetic)."""
    d = np.subtract(points, point, out=work)
    along = d @ axis
    d -= along[:, None] * axis  # = d - np.outer(along, axis), in place
    np.multiply(d, d, out=d)
    return np.sqrt(np.add.reduce(d, axis=1))  # = np.linalg.norm(d, axis=1), without its copy


def radial_jacobian(points: np.ndarray, point: np.ndarray, axis: np.ndarray, u: np.ndarray,
                    v: np.ndarray, axis_norm: float) -> np.ndarray:
    """Derivatives (N, 5) of the radial residual ``|d - (d·a) a| - r`` (d = point to each of
    ``points``) with respect to the axis point moved along ``u`` and ``v`` (mm), the unnormalized
    axis ``a0 + p2 u + p3 v`` of length ``axis_norm`` tilted along ``u`` and ``v``, and the
    radius. With ``e`` the unit radial direction (orthogonal to the axis) and ``t = d·a``:
    ∂/∂point = -e, ∂/∂axis = -t (I - a aᵀ) e / |a| = -t e / |a|, ∂/∂r = -1."""
    d = points - point
    t = d @ axis
    d -= t[:, None] * axis  # the radial vector
    rho = np.sqrt(np.einsum("ij,ij->i", d, d))
    d /= np.maximum(rho, 1e-12)[:, None]  # e
    eu, ev = d @ u, d @ v
    t /= -axis_norm
    return np.column_stack([-eu, -ev, t * eu, t * ev, np.full(len(points), -1.0)])


def fit_cylinder(points: np.ndarray, axis_guess=(0.0, 0.0, 1.0)) -> CylinderFit:
    """Fit a cylinder to ``points`` (N, 3, mm), starting from an axis along ``axis_guess``
    through the centroid. Robust to a few outliers (soft-L1 loss)."""
    pts = np.asarray(points, float)
    c = pts.mean(axis=0)
    a0 = np.asarray(axis_guess, float)
    a0 /= np.linalg.norm(a0)
    # two unit vectors orthogonal to the axis guess parameterize the axis tilt and offset
    u = np.cross(a0, [1.0, 0, 0] if abs(a0[0]) < 0.9 else [0, 1.0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(a0, u)

    def line(p):
        axis = a0 + p[2] * u + p[3] * v
        axis /= np.linalg.norm(axis)
        return c + p[0] * u + p[1] * v, axis

    work = np.empty_like(pts)

    def residual(p):
        point, axis = line(p)
        return radial_distance(pts, point, axis, work) - p[4]

    def jacobian(p):
        point, axis = line(p)
        return radial_jacobian(pts, point, axis, u, v, np.linalg.norm(a0 + p[2] * u + p[3] * v))

    r0 = float(np.median(radial_distance(pts, c, a0)))
    sol = least_squares(residual, [0, 0, 0, 0, r0], jac=jacobian, loss="soft_l1", f_scale=0.05)
    point, axis = line(sol.x)
    res = residual(sol.x)
    return CylinderFit(point, axis, float(sol.x[4]), float(np.sqrt(np.mean(res ** 2))))
