"""Rig calibration: camera and projector lenses, their relative pose, and the turntable axis.

Coordinate frames (all lengths in mm):

* **camera frame** — origin at the camera's centre of projection, z along the optical axis.
* **projector frame** — ``X_p = R @ X_c + T`` maps camera-frame points to the projector frame.
* **stage frame** — origin on the turntable axis at the stage plate (``axis_point``), z along
  ``axis_direction`` (pointing from the plate towards the sample), x towards the camera's
  centre (perpendicular to z), y = z × x. A stage moved to angle θ (degrees, right-handed about
  +z) shows the sample point ``S`` (sample frame, i.e. stage frame at θ = 0) at ``Rz(θ) @ S``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dotshell.errors import CalibrationError
from dotshell.geometry.lens import Lens

FORMAT = "dotshell-calibration/1"
#: The turntable axis of a calibration that has none (see ``RigCalibration.axis_measured``).
PLACEHOLDER_AXIS_POINT = (0.0, 0.0, 1000.0)
PLACEHOLDER_AXIS_DIRECTION = (0.0, -1.0, 0.0)


def rot_z(degrees: float) -> np.ndarray:
    """3x3 rotation about +z by ``degrees`` (right-handed)."""
    a = np.deg2rad(degrees)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class RigCalibration:
    """Everything reconstruction needs to turn correspondences into stage-frame points.

    Attributes:
        camera: camera lens.
        projector: projector lens (an inverse camera).
        R: 3x3 rotation, camera frame → projector frame.
        T: translation (mm), camera frame → projector frame.
        axis_point: a point on the turntable axis at the stage plate, camera frame (mm).
        axis_direction: unit direction of the turntable axis, camera frame, plate → sample.
        source: where this calibration came from (``"ground-truth"``, a file path, ...).
        rms: RMS errors of the solve by name (pixels), empty for ground truth.
        axis_measured: False when the rig's turntable axis was not calibrated (no turntable
            frames, an OpenCV file without one): ``axis_point`` / ``axis_direction`` are then a
            placeholder (the camera's −y axis through (0, 0, 1000) mm) that single-view,
            camera-frame reconstruction ignores and turntable scans must not use.
    """

    camera: Lens
    projector: Lens
    R: np.ndarray
    T: np.ndarray
    axis_point: np.ndarray
    axis_direction: np.ndarray
    source: str = "ground-truth"
    rms: dict | None = None
    axis_measured: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "R", np.asarray(self.R, float).reshape(3, 3))
        object.__setattr__(self, "T", np.asarray(self.T, float).reshape(3))
        object.__setattr__(self, "axis_point", np.asarray(self.axis_point, float).reshape(3))
        d = np.asarray(self.axis_direction, float).reshape(3)
        with np.errstate(invalid="ignore", divide="ignore"):
            object.__setattr__(self, "axis_direction", d / np.linalg.norm(d))

    @property
    def projector_centre(self) -> np.ndarray:
        """Projector centre of projection in the camera frame (mm)."""
        return -self.R.T @ self.T

    @property
    def baseline_mm(self) -> float:
        """Distance between camera and projector centres (mm)."""
        return float(np.linalg.norm(self.T))

    def stage_basis(self) -> np.ndarray:
        """3x3 matrix whose rows are the stage frame's x, y, z axes in the camera frame."""
        z = self.axis_direction
        to_cam = -self.axis_point
        x = to_cam - z * (to_cam @ z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        return np.vstack([x, y, z])

    def sample_rotation(self, angle_deg: float) -> np.ndarray:
        """3x3 rotation taking sample-frame directions to the camera frame with the stage at θ
        degrees (``d_camera = R @ d_sample``; row vectors: ``d_sample = d_camera @ R``)."""
        return self.stage_basis().T @ rot_z(angle_deg)

    def camera_to_sample(self, points: np.ndarray, angle_deg: float) -> np.ndarray:
        """Camera-frame points (N, 3) seen at stage angle θ → sample (stage at 0°) frame (mm)."""
        aligned = (np.asarray(points, float) - self.axis_point) @ self.stage_basis().T
        return aligned @ rot_z(angle_deg)  # row-vector form of rot_z(-θ) @ p

    def sample_to_camera(self, points: np.ndarray, angle_deg: float) -> np.ndarray:
        """Sample-frame points (N, 3) → camera frame (mm) with the stage at θ degrees."""
        aligned = np.asarray(points, float) @ rot_z(angle_deg).T
        return aligned @ self.stage_basis() + self.axis_point

    def to_dict(self) -> dict:
        return {
            "format": FORMAT,
            "source": self.source,
            "units": "mm, pixels",
            "camera": self.camera.to_dict(),
            "projector": self.projector.to_dict(),
            "R": self.R.tolist(),
            "T": self.T.tolist(),
            "turntable": {
                "axis_point": self.axis_point.tolist(),
                "axis_direction": self.axis_direction.tolist(),
                "measured": self.axis_measured,
            },
            "rms": self.rms or {},
        }

    @classmethod
    def from_dict(cls, d: dict, where: str = "calibration") -> RigCalibration:
        if not isinstance(d, dict):
            raise CalibrationError(f"{where}: a calibration is a JSON object, not a "
                                   f"{type(d).__name__}. Write one with `dotshell calibrate`.")
        if d.get("format") != FORMAT:
            raise CalibrationError(
                f"{where}: not a dotshell calibration (expected format {FORMAT!r}, found "
                f"{d.get('format')!r}). Write one with `dotshell scan` or convert it first.")
        try:
            calib = cls(
                camera=Lens.from_dict(d["camera"]),
                projector=Lens.from_dict(d["projector"]),
                R=d["R"], T=d["T"],
                axis_point=d["turntable"]["axis_point"],
                axis_direction=d["turntable"]["axis_direction"],
                source=d.get("source", where), rms=d.get("rms") or None,
                axis_measured=bool(d["turntable"].get("measured", True)),
            )
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise CalibrationError(
                f"{where}: calibration is incomplete or malformed ({type(exc).__name__}: {exc}). "
                "It needs camera, projector (width, height, K, dist), R, T and turntable "
                "(axis_point, axis_direction).") from None
        problem = calib.problem()
        if problem:
            raise CalibrationError(f"{where}: {problem}. Re-solve it with `dotshell calibrate` "
                                   "or restore the file.")
        return calib

    def problem(self) -> str:
        """What makes this calibration unusable, or ''."""
        for name, lens in (("camera", self.camera), ("projector", self.projector)):
            K = np.asarray(lens.K, float)
            if not (np.all(np.isfinite(K)) and np.all(np.isfinite(lens.dist))):
                return f"the {name} matrix or distortion holds NaN or infinity"
            if K[0, 0] <= 0 or K[1, 1] <= 0 or lens.width < 1 or lens.height < 1:
                return f"the {name} has a non-positive focal length or size"
        arrays = (self.R, self.T, self.axis_point, self.axis_direction)
        if not all(np.all(np.isfinite(a)) for a in arrays):
            return "R, T or the turntable axis holds NaN or infinity (or a zero axis direction)"
        if not np.allclose(self.R @ self.R.T, np.eye(3), atol=1e-6) or np.linalg.det(self.R) < 0:
            return "R is not a rotation matrix"
        if self.baseline_mm <= 0:
            return "the camera and projector are at the same place (T = 0): no baseline"
        return ""

    def save(self, path: Path) -> None:
        from dotshell.run.store import atomic_write_text

        atomic_write_text(Path(path), json.dumps(self.to_dict(), indent=2))

    @classmethod
    def load(cls, path: Path) -> RigCalibration:
        path = Path(path)
        if path.is_dir():
            raise CalibrationError(f"calibration file {path} is a directory, not a file. Give "
                                   "the path of a calibration.json written by dotshell.")
        if path.exists() and not path.is_file():
            raise CalibrationError(f"calibration file {path} is not a regular file (a device, "
                                   "FIFO or socket). Give the path of a calibration.json written "
                                   "by dotshell.")
        if not path.is_file():
            raise CalibrationError(f"calibration file {path} does not exist. Give the path of a "
                                   "calibration.json written by dotshell.")
        try:
            data = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
            raise CalibrationError(f"calibration file {path} is not valid JSON ({exc}). Write it "
                                   "again with `dotshell calibrate`, or restore it from a "
                                   "backup.") from None
        return cls.from_dict(data, where=str(path))
