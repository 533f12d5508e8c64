"""Pinhole lens models with Brown–Conrady distortion (OpenCV's convention).

A camera and a projector are both a :class:`Lens`: a projector is an inverse camera. Pixel
coordinates follow OpenCV: the centre of the top-left pixel is (0, 0), x to the right, y down.
All lengths are in millimetres, all pixel quantities in pixels.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np


@dataclass(frozen=True)
class Lens:
    """Intrinsics of a camera or projector.

    Attributes:
        K: 3x3 intrinsic matrix (fx, fy, cx, cy in pixels).
        dist: distortion coefficients (k1, k2, p1, p2, k3), OpenCV order; unitless.
        width: image width in pixels.
        height: image height in pixels.
    """

    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    width: int = 0
    height: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", np.asarray(self.K, dtype=np.float64).reshape(3, 3))
        d = np.zeros(5)
        given = np.asarray(self.dist, dtype=np.float64).ravel()
        d[: min(5, given.size)] = given[:5]
        object.__setattr__(self, "dist", d)

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return (self.width, self.height)

    def undistort(self, pixels: np.ndarray) -> np.ndarray:
        """Distorted pixel coordinates (N, 2) → ideal normalized coordinates (N, 2), unitless."""
        pts = np.ascontiguousarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
        if pts.shape[0] == 0:
            return np.zeros((0, 2))
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-10)
        out = cv2.undistortPoints(pts, self.K, self.dist, criteria=crit)
        return out.reshape(-1, 2)

    def rays(self, pixels: np.ndarray) -> np.ndarray:
        """Unit ray directions (N, 3) in the lens frame for distorted pixel coordinates (N, 2)."""
        n = self.undistort(pixels)
        d = np.column_stack([n, np.ones(len(n))])
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def project(self, points: np.ndarray) -> np.ndarray:
        """Points (N, 3) in the lens frame (mm) → distorted pixel coordinates (N, 2)."""
        return project_points(self.K, self.dist, points)

    def scaled(self, factor: float) -> "Lens":
        """The same lens seen at ``factor`` times the resolution (for reduced-size tests)."""
        K = self.K.copy()
        K[0, 0] *= factor
        K[1, 1] *= factor
        K[0, 2] = (K[0, 2] + 0.5) * factor - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * factor - 0.5
        return Lens(K, self.dist.copy(), round(self.width * factor), round(self.height * factor))

    def to_dict(self) -> dict:
        return {
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "Lens":
        return cls(np.array(d["K"], float), np.array(d.get("dist", [0] * 5), float),
                   int(d["width"]), int(d["height"]))


def lens_from_fov(width: int, height: int, fx: float, dist=(0, 0, 0, 0, 0),
                  cx: float | None = None, cy: float | None = None) -> Lens:
    """A lens with square pixels, focal length ``fx`` (pixels) and principal point (cx, cy)
    (pixels; the image centre when omitted)."""
    cx = (width - 1) / 2 if cx is None else cx
    cy = (height - 1) / 2 if cy is None else cy
    K = np.array([[fx, 0, cx], [0, fx, cy], [0, 0, 1.0]])
    return Lens(K, np.asarray(dist, float), width, height)


def project_points(K: np.ndarray, dist, points: np.ndarray) -> np.ndarray:
    """OpenCV's pinhole + radial/tangential model (``dist`` = k1, k2, p1, p2, k3): points
    (N, 3) in the lens frame (mm) → distorted pixel coordinates (N, 2). For solvers that vary
    ``K`` and ``dist``; otherwise use :meth:`Lens.project`."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    x = pts[:, 0] / pts[:, 2]
    y = pts[:, 1] / pts[:, 2]
    k1, k2, p1, p2, k3 = dist
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.column_stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]])
