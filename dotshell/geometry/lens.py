"""Pinhole lens models with OpenCV's distortion models: Brown–Conrady (k1, k2, p1, p2, k3), the
rational model (k4, k5, k6) and thin prism terms (s1..s4). OpenCV's tilted-sensor terms (τx, τy)
are refused when not zero: nothing downstream applies them.

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
        dist: distortion coefficients in OpenCV's order, unitless: 5 (k1, k2, p1, p2, k3) or,
            when the rational or thin prism terms are used, 12 (… k4, k5, k6, s1, s2, s3, s4).
            Any of OpenCV's lengths (4, 5, 8, 12, 14) is accepted; see :func:`distortion`.
        width: image width in pixels.
        height: image height in pixels.
    """

    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    width: int = 0
    height: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", np.asarray(self.K, dtype=np.float64).reshape(3, 3))
        object.__setattr__(self, "dist", distortion(self.dist))
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not float(value).is_integer():
                raise ValueError(f"{name} {value!r} is not a whole number of pixels")
            object.__setattr__(self, name, int(value))

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

    def scaled(self, factor: float) -> Lens:
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
    def from_dict(cls, d: dict) -> Lens:
        return cls(np.array(d["K"], float), np.array(d.get("dist", [0] * 5), float),
                   d["width"], d["height"])


#: OpenCV's distortion terms in its order, and the lengths its functions take.
DISTORTION_TERMS = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4",
                    "tau_x", "tau_y")
OPENCV_DISTORTION_LENGTHS = (4, 5, 8, 12, 14)


def distortion(given) -> np.ndarray:
    """OpenCV distortion coefficients of any of OpenCV's lengths (4, 5, 8, 12, 14) as dotshell
    keeps them: 5 terms (Brown–Conrady) when the rational and thin prism terms are all zero,
    else 12. Raises ValueError naming the terms for another length or a tilted sensor (τx, τy
    not zero), which nothing downstream applies."""
    d = np.asarray(given, dtype=np.float64).ravel()
    if d.size not in OPENCV_DISTORTION_LENGTHS and d.size > 5:
        raise ValueError(f"{d.size} distortion terms: OpenCV's models have 4, 5, 8, 12 or 14 "
                         f"({', '.join(DISTORTION_TERMS)})")
    if d.size == 14 and np.any(d[12:] != 0):
        raise ValueError(f"tilted-sensor distortion (tau_x = {d[12]:g}, tau_y = {d[13]:g}) is "
                         "not supported; calibrate without CALIB_TILTED_MODEL")
    full = np.zeros(12)
    full[: min(12, d.size)] = d[:12]
    return full if np.any(full[5:] != 0) else full[:5].copy()


def distort_normalized(dist: np.ndarray, x: np.ndarray, y: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's distortion of ideal normalized coordinates (x, y) → distorted ones (unitless),
    ``dist`` of 5 or 12 terms (:func:`distortion`)."""
    k1, k2, p1, p2, k3 = dist[:5]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    prism_x = prism_y = 0.0
    if len(dist) > 5:  # the rational model's denominator and the thin prism terms
        k4, k5, k6, s1, s2, s3, s4 = dist[5:12]
        radial = radial / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        prism_x, prism_y = r2 * (s1 + r2 * s2), r2 * (s3 + r2 * s4)
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) + prism_x
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y + prism_y
    return xd, yd


def lens_from_fov(width: int, height: int, fx: float, dist=(0, 0, 0, 0, 0),
                  cx: float | None = None, cy: float | None = None) -> Lens:
    """A lens with square pixels, focal length ``fx`` (pixels) and principal point (cx, cy)
    (pixels; the image centre when omitted)."""
    cx = (width - 1) / 2 if cx is None else cx
    cy = (height - 1) / 2 if cy is None else cy
    K = np.array([[fx, 0, cx], [0, fx, cy], [0, 0, 1.0]])
    return Lens(K, np.asarray(dist, float), width, height)


def project_points(K: np.ndarray, dist, points: np.ndarray) -> np.ndarray:
    """OpenCV's pinhole model with its distortion (``dist`` of 5 or 12 terms, see
    :func:`distortion`): points (N, 3) in the lens frame (mm) → distorted pixel coordinates
    (N, 2). For solvers that vary ``K`` and ``dist``; otherwise use :meth:`Lens.project`."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    xd, yd = distort_normalized(dist, pts[:, 0] / pts[:, 2], pts[:, 1] / pts[:, 2])
    return np.column_stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]])
