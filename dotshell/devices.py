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
