"""Shape fits for validation: radius about a known axis, and a free least-squares cylinder."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: the robust loss's scale (mm): residuals well below it count as squares, far above it
#: linearly (soft-L1, ``2·f²·(√(1 + (r/f)²) − 1)``)
LOSS_SCALE_MM = 0.05
#: the fit stops when a step moves the axis point and radius by less than this (mm) and turns
#: the axis by less than this (radians)
STEP_TOLERANCE = 1e-9
MAX_ITERATIONS = 100


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
    ``work``: an (N, 3) float64 scratch array to compute in (a fit calls this several times;
    a fresh 5 MB array each time costs more in page faults than the arithmetic)."""
    d = np.subtract(points, point, out=work)
    along = d @ axis
    d -= along[:, None] * axis  # = d - np.outer(along, axis), in place
    np.multiply(d, d, out=d)
    return np.sqrt(np.add.reduce(d, axis=1))  # = np.linalg.norm(d, axis=1), without its copy


class _CylinderModel:
    """The residuals ``distance from the axis − radius`` (mm) of the points and their
    Jacobian in the five parameters (axis-point offsets along ``u`` and ``v`` through the
    centroid, mm; axis tilts along ``u`` and ``v``, radians for small tilts; radius, mm)."""

    def __init__(self, pts: np.ndarray, axis_guess: np.ndarray) -> None:
        self.pts = pts
        self.centroid = pts.mean(axis=0)
        self.a0 = axis_guess
        # two unit vectors orthogonal to the axis guess parameterize the axis tilt and offset
        u = np.cross(axis_guess, [1.0, 0, 0] if abs(axis_guess[0]) < 0.9 else [0, 1.0, 0])
        self.u = u / np.linalg.norm(u)
        self.v = np.cross(axis_guess, self.u)
        self.work = np.empty_like(pts)
        self.jac = np.empty((len(pts), 5))  # reused: fresh (N, 5) arrays cost page faults
        self.weighted = np.empty((len(pts), 5))

    def line(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """(axis point, unit axis, length of the unnormalized axis) of parameters ``p``."""
        axis = self.a0 + p[2] * self.u + p[3] * self.v
        length = float(np.linalg.norm(axis))
        return self.centroid + p[0] * self.u + p[1] * self.v, axis / length, length

    def residuals(self, p: np.ndarray) -> np.ndarray:
        point, axis, _ = self.line(p)
        return radial_distance(self.pts, point, axis, self.work) - p[4]

    def linearized(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(residuals (N,), Jacobian (N, 5)) at ``p``; the Jacobian is overwritten by the next
        call. With ``w`` the point's offset from the axis and ``e = w/|w|``: ∂r/∂(offset along
        u) = −e·u, ∂r/∂(tilt along u) = −(d·axis)(e·u)/length (likewise for v),
        ∂r/∂radius = −1."""
        point, axis, length = self.line(p)
        d = np.subtract(self.pts, point, out=self.work)
        along = d @ axis
        d -= along[:, None] * axis  # w
        dist = np.sqrt(np.einsum("ij,ij->i", d, d))
        jac = self.jac
        inv = 1.0 / np.maximum(dist, 1e-12)
        np.multiply(d @ self.u, -inv, out=jac[:, 0])
        np.multiply(d @ self.v, -inv, out=jac[:, 1])
        along /= length
        np.multiply(jac[:, 0], along, out=jac[:, 2])
        np.multiply(jac[:, 1], along, out=jac[:, 3])
        jac[:, 4] = -1.0
        dist -= p[4]
        return dist, jac


def _soft_l1_cost(r: np.ndarray) -> float:
    z = np.square(r / LOSS_SCALE_MM)
    return float(np.sum(np.sqrt(1.0 + z) - 1.0))


def fit_cylinder(points: np.ndarray, axis_guess=(0.0, 0.0, 1.0)) -> CylinderFit:
    """Fit a cylinder to ``points`` (N, 3, mm), starting from an axis along ``axis_guess``
    through the centroid. Robust to a few outliers: it minimizes the soft-L1 loss of the radial
    residuals (scale :data:`LOSS_SCALE_MM`) by Gauss–Newton steps with the loss's weights
    (iteratively reweighted least squares, each step halved until it lowers the loss)."""
    pts = np.asarray(points, float)
    a0 = np.asarray(axis_guess, float)
    model = _CylinderModel(pts, a0 / np.linalg.norm(a0))
    p = np.zeros(5)
    p[4] = float(np.median(radial_distance(pts, model.centroid, model.a0, model.work)))
    r, jac = model.linearized(p)
    cost = _soft_l1_cost(r)
    for _ in range(MAX_ITERATIONS):
        weight = 1.0 / np.sqrt(1.0 + np.square(r / LOSS_SCALE_MM))  # the loss's d/d(r²)
        wj = np.multiply(jac, weight[:, None], out=model.weighted)
        step = np.linalg.lstsq(wj.T @ jac, -(wj.T @ r), rcond=None)[0]
        r_trial, jac_new = model.linearized(p + step)  # accepted steps (all but a few) need it
        jac_trial: np.ndarray | None = jac_new
        cost_trial = _soft_l1_cost(r_trial)
        while cost_trial > cost and np.abs(step).max() >= STEP_TOLERANCE:
            step /= 2.0
            r_trial = model.residuals(p + step)
            cost_trial = _soft_l1_cost(r_trial)
            jac_trial = None
        p, r, cost = p + step, r_trial, cost_trial
        if np.abs(step).max() < STEP_TOLERANCE:
            break
        jac = jac_trial if jac_trial is not None else model.linearized(p)[1]
    point, axis, _ = model.line(p)
    return CylinderFit(point, axis, float(p[4]), float(np.sqrt(np.mean(r ** 2))))
