"""State every camera driver of this package keeps, and the properties read from it."""

from __future__ import annotations

from typing import Any

from dotshell.devices import FrameInfo


class CameraBase:
    """The shared part of a camera driver: its validated ``settings``, frame ``size`` (width,
    height in pixels), the exposure the camera really uses (``exposure_ms``, NaN until known),
    the controls it refused (control → reason, shown in ``status()["refused_controls"]``) and
    the information on the last frame.

    ``bit_depth`` comes from ``settings["bit_depth"]``; a driver whose settings name it
    differently overrides the property."""

    def __init__(self, settings: dict[str, Any], size: tuple[int, int] = (0, 0)) -> None:
        self.settings = settings
        self.size = size
        self.exposure_ms = float("nan")
        self.refused: dict[str, str] = {}
        self._info = FrameInfo(timestamp_s=float("nan"))

    @property
    def resolution(self) -> tuple[int, int]:
        """(width, height) of the frames in pixels, as last measured (hardware-free)."""
        return self.size

    @property
    def bit_depth(self) -> int:
        """Bits per pixel of the frames (hardware-free)."""
        return int(self.settings["bit_depth"])

    def last_frame_info(self) -> FrameInfo:
        """Timestamp, frame number and exposure of the last frame returned."""
        return self._info
