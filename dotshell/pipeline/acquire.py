"""The acquisition runner: moves the stage, shows each pattern, captures and stores frames.

The runner owns the loop, events, retries and abort; the devices own the hardware. A
:class:`~dotshell.errors.DeviceError` from a capture is a recoverable per-step failure, retried
``scan.retries`` times before the scan fails. Every frame is on disk before the next is taken.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np

from dotshell.coding import PatternFrame
from dotshell.devices import ExposureControl
from dotshell.errors import DeviceError
from dotshell.events import EventBus, FrameCaptured, ViewCaptured
from dotshell.rig import Rig
from dotshell.store import RunStore


class Acquisition:
    """Captures views of a scan into a :class:`RunStore`."""

    def __init__(self, rig: Rig, patterns: list[PatternFrame], store: RunStore,
                 scan: dict[str, Any], bus: EventBus, stop: threading.Event | None = None) -> None:
        self.rig = rig
        self.patterns = patterns
        self.store = store
        self.scan = scan
        self.bus = bus
        self.stop = stop or threading.Event()
        self.seconds = 0.0
        if isinstance(rig.camera, ExposureControl):
            rig.camera.set_exposure(scan["exposure_ms"])

    def _capture(self, pattern: PatternFrame, view: int) -> np.ndarray:
        attempts = self.scan["retries"] + 1
        for attempt in range(1, attempts + 1):
            try:
                self.rig.projector.show(pattern.image)
                if self.scan["settle_ms"] > 0:
                    time.sleep(self.scan["settle_ms"] / 1000.0)
                return self.rig.camera.capture()
            except DeviceError as exc:
                if attempt == attempts:
                    raise DeviceError(f"view {view}, frame {pattern.name!r}: capture failed "
                                      f"{attempts} times; last error: {exc}") from None
                self.bus.warn(f"view {view}, frame {pattern.name!r}: {exc} — retrying "
                              f"({attempt}/{attempts - 1})")
        raise AssertionError("unreachable")

    def run_view(self, view: int, angle_deg: float) -> list[np.ndarray] | None:
        """Capture all frames of one view; None if the scan was stopped midway (frames taken
        so far stay on disk and the view is marked incomplete)."""
        t0 = time.perf_counter()
        self.rig.stage.move_to(angle_deg)
        frames: list[np.ndarray] = []
        try:
            for i, pattern in enumerate(self.patterns):
                if self.stop.is_set():
                    return None
                frame = self._capture(pattern, view)
                self.store.write_frame(view, i, pattern.name, frame)
                frames.append(frame)
                self.bus.emit(FrameCaptured(view=view, index=i, name=pattern.name))
        finally:
            complete = len(frames) == len(self.patterns)
            self.store.mark_view(view, len(frames), complete)
            self.seconds += time.perf_counter() - t0
        self.bus.emit(ViewCaptured(view=view, angle_deg=angle_deg, n_frames=len(frames)))
        return frames
