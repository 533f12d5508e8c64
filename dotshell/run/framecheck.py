"""What a run's frames must be, checked wherever frames enter a run: from the camera during a
scan or a resume (fringe, trans-illumination and flat-field frames) and from the run's files
when they are processed again.

A frame is a 2-D ``uint8`` array for an 8-bit camera, ``uint16`` for a 9- to 16-bit one, with
values below ``2**bit_depth``, the camera's size (width × height pixels). One wrong frame — an
8-bit frame in a 12-bit run, a colour frame, a frame of another size — would silently change
the result (a lower contrast decoded as shadow, a saturation level never reached), so it is
refused with a :class:`~dotshell.errors.FrameError` naming the frame, what it is, what the run
expects and the fix.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from dotshell.errors import FrameError


def dtype_for(bit_depth: int) -> type:
    """The array type of frames of a ``bit_depth``-bit camera."""
    return np.uint8 if bit_depth <= 8 else np.uint16


@dataclass(frozen=True)
class FrameSpec:
    """The frames of one run: ``width`` × ``height`` pixels, ``bit_depth`` bits."""

    width: int
    height: int
    bit_depth: int

    @classmethod
    def of_camera(cls, camera: Any) -> FrameSpec:
        """What ``camera`` says its frames are (its hardware-free properties)."""
        w, h = camera.resolution
        return cls(int(w), int(h), int(camera.bit_depth))

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> FrameSpec:
        return cls(int(d["width"]), int(d["height"]), int(d["bit_depth"]))

    def to_dict(self) -> dict[str, int]:
        return {"width": self.width, "height": self.height, "bit_depth": self.bit_depth}

    def check(self, frame: Any, label: str, fix: str) -> np.ndarray:
        """``frame`` as a 2-D array if it is one of this run's frames (an (H, W, 1) array is
        taken as the (H, W) frame it is), else a :class:`FrameError`: "``label`` is <what it
        is>; <what the run expects>. ``fix``"."""
        if isinstance(frame, np.ndarray) and frame.ndim == 3 and frame.shape[2] == 1:
            frame = frame[:, :, 0]
        problem = self.problem(frame)
        if problem:
            raise FrameError(f"{label} {problem}. {fix}")
        return frame

    def problem(self, frame: Any) -> str:
        """What is wrong with ``frame`` for this run ('' if nothing): "is ...; ..."."""
        want = f"{self.width}x{self.height} px {np.dtype(dtype_for(self.bit_depth)).name} " \
               f"arrays, {self.bit_depth} bit"
        if not isinstance(frame, np.ndarray):
            return f"is a {type(frame).__name__}, not an image: frames are {want}"
        if frame.ndim == 3 and frame.shape[2] in (3, 4):
            return (f"is a colour image ({frame.shape[2]} channels); the run needs monochrome "
                    f"frames ({want}): set the camera to a monochrome pixel format (Mono8, "
                    "Mono12, Mono16)")
        if frame.ndim != 2:
            return f"is a {frame.ndim}-D array of shape {frame.shape}; frames are {want}"
        if frame.dtype not in (np.uint8, np.uint16):
            return f"is {frame.dtype.name}; frames are uint8 or uint16 ({want})"
        h, w = frame.shape
        if (w, h) != (self.width, self.height):
            return (f"is {w}x{h} px but the camera's resolution is {self.width}x{self.height} "
                    "px (width x height)")
        bits = 8 if frame.dtype == np.uint8 else 16
        if frame.dtype != dtype_for(self.bit_depth):
            return (f"is {frame.dtype.name} ({bits} bit) but the camera reports "
                    f"{self.bit_depth} bit ({np.dtype(dtype_for(self.bit_depth)).name}): mixed "
                    "bit depths would silently change contrast and saturation; make the "
                    "camera's pixel format and its bit_depth agree")
        top = int(frame.max()) if frame.size else 0
        if top >= 1 << self.bit_depth:
            return (f"holds values up to {top} but the camera reports {self.bit_depth} bit "
                    f"(0..{(1 << self.bit_depth) - 1}): set bit_depth to the camera's real "
                    "depth")
        return ""
