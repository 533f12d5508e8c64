"""A simulated camera that misbehaves as real ones do, to prove the frame-integrity checks
(:mod:`dotshell.run.integrity`): backend ``sim-camera-faulty``, the ``sim-camera`` with
three settings more.

Faults (``fault``), each happening once, at the ``fault_at_frame``-th frame since connect:

* ``late``: the camera falls one frame behind for ``fault_frames`` frames — each returns the
  image and metadata of the frame before — then catches up by dropping one frame (a driver
  reading its buffer one frame late).
* ``reset``: the frame counter restarts at 0 (a re-plugged or restarted camera) and the first
  frame after the restart is the stale image left in the buffer from before it.
* ``duplicate``: one frame is delivered twice (the same buffer returned again, metadata
  included).

Frames reach the rig through the same path whether captured one by one or triggered.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from dotshell.devices import FrameInfo
from dotshell.settings import Setting

from dotshell_sim.devices import CAMERA_SCHEMA, SimCamera

FAULTS = ("none", "late", "reset", "duplicate")

FAULTY_CAMERA_SCHEMA: dict[str, Setting] = {
    **CAMERA_SCHEMA,
    "fault": Setting("str", "none", "the fault to show once (docs/devices.md)", choices=FAULTS),
    "fault_at_frame": Setting("int", 0, "the frame (counted from connect, from 0) the fault "
                              "starts at", min=0),
    "fault_frames": Setting("int", 8, "late: how many frames come one frame behind", min=1),
}


class FrameFault:
    """Passes a camera's frames through, spoiling them as its ``kind`` says (see the module
    docstring). ``frames`` counts the frames seen."""

    def __init__(self, kind: str, at_frame: int, length: int) -> None:
        self.kind, self.at, self.length = kind, at_frame, length
        self.frames = 0
        self.id_offset = 0
        self._previous: tuple[np.ndarray, FrameInfo] | None = None

    def __call__(self, frame: np.ndarray, info: FrameInfo) -> tuple[np.ndarray, FrameInfo]:
        n, self.frames = self.frames, self.frames + 1
        previous, self._previous = self._previous, (frame, info)
        if previous is None or self.kind == "none":
            return frame, info
        if self.kind == "duplicate" and n == self.at:
            self._previous = previous
            return previous
        if self.kind == "late" and self.at <= n < self.at + self.length:
            return previous  # what the driver reads: the buffer before this one
        if self.kind == "reset" and n == self.at:
            self.id_offset = info.frame_id
            return previous[0], dataclasses.replace(info, frame_id=0)
        if self.id_offset:
            return frame, dataclasses.replace(info, frame_id=info.frame_id - self.id_offset)
        return frame, info


class FaultySimCamera(SimCamera):
    """The sim camera with a :class:`FrameFault` on its output."""

    name = "sim-camera-faulty"

    def __init__(self, settings: dict, world: Any) -> None:
        super().__init__(settings, world)
        self.fault = FrameFault(settings["fault"], settings["fault_at_frame"],
                                settings["fault_frames"])

    def capture(self) -> np.ndarray:
        frame, self._info = self.fault(super().capture(), self._info)
        return frame

    def read_armed(self, timeout_s: float) -> list[tuple[np.ndarray, FrameInfo]]:
        return [self.fault(frame, info) for frame, info in super().read_armed(timeout_s)]


def make_faulty_camera(settings: dict | None = None, context: Any = None) -> FaultySimCamera:
    from dotshell_sim.devices import _factory

    return _factory(FaultySimCamera, FAULTY_CAMERA_SCHEMA, "sim-camera-faulty")(settings,
                                                                                   context)
