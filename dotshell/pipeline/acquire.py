"""The acquisition runner: moves the stage, shows each pattern, captures and stores frames.

The runner owns the loop, events, retries and abort; the devices own the hardware. A
:class:`~dotshell.errors.DeviceError` from a capture is a recoverable per-step failure, retried
``scan.retries`` times before the scan fails. Frames go to a writer thread (PNG encoding
overlaps the next capture) through a small bounded queue; a view is reported captured only when
all its frames are on disk, and every exit path — done, stopped, failed, Ctrl-C — drains the
queue first, so nothing captured is lost.
"""

from __future__ import annotations

import queue
import threading
import time
from typing import Any

import numpy as np

from dotshell.coding import PatternFrame
from dotshell.devices import ExposureControl
from dotshell.errors import DeviceError, RunError
from dotshell.events import EventBus, FrameCaptured, ViewCaptured
from dotshell.rig import Rig
from dotshell.store import RunStore


class FrameWriter:
    """Writes frames to a :class:`RunStore` on a background thread, in order."""

    def __init__(self, store: RunStore, depth: int = 4) -> None:
        self.store = store
        self.queue: queue.Queue = queue.Queue(maxsize=depth)
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, name="dotshell-frame-writer", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while True:
            item = self.queue.get()
            try:
                if item is None:
                    return
                if self.error is None:
                    self.store.write_frame(*item)
            except OSError as exc:  # disk full, permissions, unplugged drive
                self.error = RunError(f"could not write frame {item[2]!r} of view {item[0]} to "
                                      f"{self.store.root}: {exc}. Free disk space or scan with "
                                      "--out on another drive; frames already written are kept.")
            except BaseException as exc:  # reported to the runner on its next call
                self.error = exc
            finally:
                self.queue.task_done()

    def put(self, view: int, index: int, name: str, image: np.ndarray) -> None:
        self.check()
        self.queue.put((view, index, name, image))

    def check(self) -> None:
        if self.error is not None:
            raise self.error

    def close(self) -> None:
        self.queue.join()
        self.queue.put(None)
        self.thread.join()


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
        self.writer = FrameWriter(store)
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
                self.writer.put(view, i, pattern.name, frame)
                frames.append(frame)
                self.bus.emit(FrameCaptured(view=view, index=i, name=pattern.name))
        finally:
            self.writer.queue.join()  # every frame taken is on disk before we go on
            complete = len(frames) == len(self.patterns)
            self.store.mark_view(view, len(frames), complete)
            self.seconds += time.perf_counter() - t0
        self.writer.check()
        self.bus.emit(ViewCaptured(view=view, angle_deg=angle_deg, n_frames=len(frames)))
        return frames

    def close(self) -> None:
        """Stop the writer thread (after it wrote everything queued)."""
        self.writer.close()
