"""Device roles as small protocols (structural typing: a backend needs no base class).

Every device has ``connect()``, ``close()`` and ``status()``. Optional abilities are separate
protocols that a backend may also satisfy; the core checks them with ``isinstance``.
Units: angles in degrees, times in milliseconds, images as numpy arrays (rows, columns).
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Device(Protocol):
    def connect(self) -> None:
        """Open the device. Raise :class:`dotshell.errors.DeviceError` with a fix on failure."""
        ...

    def close(self) -> None:
        """Release the device; must be safe to call twice and after a failed connect."""
        ...

    def status(self) -> dict[str, Any]:
        """Live state for front ends, e.g. ``{"connected": True, "angle_deg": 30.0}``."""
        ...


@runtime_checkable
class Camera(Device, Protocol):
    @property
    def resolution(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        ...

    @property
    def bit_depth(self) -> int:
        """Bits per pixel of captured frames (8 → uint8, more → uint16)."""
        ...

    def capture(self) -> np.ndarray:
        """Expose and read one frame (2-D, uint8 or uint16)."""
        ...


@runtime_checkable
class Projector(Device, Protocol):
    @property
    def resolution(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        ...

    def show(self, pattern: np.ndarray) -> None:
        """Display a uint8 (height, width) image until the next call."""
        ...


@runtime_checkable
class Stage(Device, Protocol):
    def move_to(self, degrees: float) -> None:
        """Rotate to an absolute angle (degrees) and return when settled."""
        ...

    @property
    def position(self) -> float:
        """Current angle in degrees."""
        ...


@runtime_checkable
class Analyzer(Device, Protocol):
    def set_angle(self, degrees: float) -> None:
        """Set the analyzer's transmission axis relative to the polarizer (degrees)."""
        ...


@runtime_checkable
class LightSource(Device, Protocol):
    def set(self, on: bool) -> None:
        """Switch the source (e.g. trans-illumination laser) on or off."""
        ...


# ---- optional capabilities -------------------------------------------------------------------

@runtime_checkable
class ExposureControl(Protocol):
    def set_exposure(self, ms: float) -> None:
        """Set the exposure time in milliseconds."""
        ...


@runtime_checkable
class Homing(Protocol):
    def home(self) -> None:
        """Find the stage's reference position (0°)."""
        ...


@runtime_checkable
class GroundTruth(Protocol):
    """A simulated device that knows the true rig geometry (the simulator's camera)."""

    def ground_truth_calibration(self):  # -> dotshell.geometry.calibration.RigCalibration
        ...


@runtime_checkable
class Targetable(Protocol):
    """A light source whose beam can be pointed (galvo mirrors, a translation stage)."""

    def aim(self, target_mm: tuple[float, float]) -> None:
        """Point the beam at ``target_mm`` = (lateral, height) in mm in the source's own target
        plane (for the simulator: the stage frame's y and z, the beam entering the far side and
        running along +x, towards the camera). Return when the beam has settled."""
        ...


@runtime_checkable
class FlatFieldReference(Protocol):
    """A rig that can show the camera a uniform radiance field (a diffuser or integrating
    sphere port in front of the lens) for flat-field / vignetting correction."""

    def flat_field(self, on: bool) -> None:
        """Put the uniform reference in front of the camera (True) or take it away (False)."""
        ...


@runtime_checkable
class TransilluminationTruth(Protocol):
    """A simulated light source that knows the true light leaving the sample."""

    def true_normal_radiance(self, angle_deg: float, target_mm: tuple[float, float],
                             points_mm: np.ndarray) -> np.ndarray:
        """True radiance leaving the sample along the surface normal (the paper's I0) at the
        sample-frame points ``points_mm`` (N, 3), snapped to the true surface, for the stage at
        ``angle_deg`` and the beam at ``target_mm``. Units: camera DN per ms of exposure that a
        dark-subtracted, flat-fielded pixel at the principal point would record from a surface
        element facing the camera squarely. NaN where a point is farther than 1 mm from the
        true surface."""
        ...
