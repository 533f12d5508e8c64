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
from pathlib import Path
from typing import Any, Callable, TypeVar

import numpy as np

from dotshell.coding import PatternFrame
from dotshell.devices import ExposureControl, accepted_kwargs
from dotshell.errors import DeviceError, ProfileError, RunError
from dotshell.events import EventBus, FrameCaptured, ScanPaused, ScanResumed, ViewCaptured
from dotshell.pipeline.pdi import Shot, plan_shots
from dotshell.pipeline.sequenced import SequencedCapture, uses_sequenced
from dotshell.rig import Rig
from dotshell.rig_checks import refused_controls
from dotshell.store import RunStore

T = TypeVar("T")


def with_retries(action: Callable[[], T], retries: int, what: str, bus: EventBus) -> T:
    """``action()``, tried again up to ``retries`` times when it raises DeviceError (a warning
    naming ``what`` per retry); the last failure is a DeviceError naming ``what``."""
    attempts = retries + 1
    for attempt in range(1, attempts + 1):
        try:
            return action()
        except DeviceError as exc:
            if attempt == attempts:
                raise DeviceError(f"{what}: capture failed {attempts} times; last error: "
                                  f"{exc}") from None
            bus.warn(f"{what}: {exc} — retrying ({attempt}/{attempts - 1})")
    raise AssertionError("unreachable")


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
                    self.store.write_image(*item)
            except OSError as exc:  # disk full, permissions, unplugged drive
                self.error = RunError(f"could not write {item[2]} to {self.store.root}: {exc}. "
                                      "Free disk space or scan with --out on another drive; "
                                      "frames already written are kept.")
            except BaseException as exc:  # reported to the runner on its next call
                self.error = exc
            finally:
                self.queue.task_done()

    def put(self, view: int, index: int, name: str, image: np.ndarray) -> None:
        """Queue a fringe frame of a view."""
        self.put_path(self.store.frame_path(view, index, name), image,
                      f"frame {name!r} of view {view}")

    def put_path(self, path: Path, image: np.ndarray, label: str) -> None:
        """Queue any captured image for ``path`` in the run; ``label`` names it in errors."""
        self.check()
        self.queue.put((path, image, label))

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
                 scan: dict[str, Any], bus: EventBus, stop: threading.Event | None = None,
                 running: threading.Event | None = None, shots: list[Shot] | None = None) -> None:
        self.rig = rig
        self.patterns = patterns
        self.shots = shots or plan_shots(patterns, scan)
        if any(s.analyzer_deg is not None for s in self.shots) and rig.analyzer is None:
            raise ProfileError(f"{rig.profile.source}: [scan] pdi = true needs an [analyzer] "
                               "in the profile (a rotating analyzer in front of the camera).")
        self.store = store
        self.scan = scan
        self.bus = bus
        self.stop = stop or threading.Event()
        self.running = running  # cleared = pause before the next frame; None = never pause
        self.seconds = 0.0
        self._analyzer_deg: float | None = None
        self.writer = FrameWriter(store)
        if isinstance(rig.camera, ExposureControl):
            rig.camera.set_exposure(scan["exposure_ms"])
        for line in refused_controls(rig):
            bus.warn(line)
        self._show_kwargs = accepted_kwargs(rig.projector.show, ("name", "index"))
        self.sequenced = (SequencedCapture(rig, patterns, self.shots, scan, bus, with_retries)
                          if uses_sequenced(rig, scan) else None)

    def _set_analyzer(self, degrees: float) -> None:
        if degrees != self._analyzer_deg:
            self._analyzer_deg = None  # unknown until the move succeeds
            self.rig.analyzer.set_angle(degrees)
            self._analyzer_deg = degrees

    def _capture(self, shot: Shot, view: int) -> np.ndarray:
        pattern = self.patterns[shot.pattern]

        def attempt() -> np.ndarray:
            try:
                if shot.analyzer_deg is not None:
                    self._set_analyzer(shot.analyzer_deg)
                ident = {"name": pattern.name, "index": shot.pattern}
                self.rig.projector.show(pattern.image, **{k: ident[k] for k in self._show_kwargs})
                if self.scan["settle_ms"] > 0:
                    time.sleep(self.scan["settle_ms"] / 1000.0)
                return self.rig.camera.capture()
            except DeviceError:
                self._analyzer_deg = None  # unknown after a failure: set it again
                raise

        return with_retries(attempt, self.scan["retries"], f"view {view}, frame {shot.name!r}",
                            self.bus)

    def _wait_if_paused(self, view: int, index: int) -> bool:
        """Block while ``running`` is cleared (a pause between frames); False if stopped
        meanwhile. Pause time is not counted in the acquisition time."""
        if self.running is None or self.running.is_set():
            return True
        self.writer.queue.join()  # frames taken before the pause are on disk while we wait
        self.bus.emit(ScanPaused(view=view, index=index))
        t0 = time.perf_counter()
        while not self.running.wait(0.05):
            if self.stop.is_set():
                return False
        self.seconds -= time.perf_counter() - t0
        self.bus.emit(ScanResumed(view=view, index=index))
        return True

    def run_view(self, view: int, angle_deg: float) -> list[np.ndarray] | None:
        """Capture all frames of one view; None if the scan was stopped midway (frames taken
        so far stay on disk and the view is marked incomplete)."""
        t0 = time.perf_counter()
        self.rig.stage.move_to(angle_deg)
        frames: list[np.ndarray] = []
        try:
            for i, shot in enumerate(self.shots):
                captured = self.sequenced is not None and self.sequenced.pending()
                if (self.stop.is_set() and not captured) or not self._wait_if_paused(view, i):
                    return None
                frame = (self.sequenced.frame(view, i, self._set_analyzer) if self.sequenced
                         else self._capture(shot, view))
                self.writer.put(view, i, shot.name, frame)
                frames.append(frame)
                self.bus.emit(FrameCaptured(view=view, index=i, name=shot.name))
        finally:
            self.writer.queue.join()  # every frame taken is on disk before we go on
            complete = len(frames) == len(self.shots)
            self.store.mark_view(view, len(frames), complete)
            self.seconds += time.perf_counter() - t0
        self.writer.check()
        self.bus.emit(ViewCaptured(view=view, angle_deg=angle_deg, n_frames=len(frames)))
        return frames

    def close(self) -> None:
        """Stop the writer thread (after it wrote everything queued)."""
        self.writer.close()
