"""The acquisition runner: moves the stage, takes each shot's frame through its engine and
stores frames.

The runner owns the loop, events, retries, frame checks and abort; its engine
(:mod:`dotshell.pipeline.engines`: show-capture or hardware-sequenced, chosen once from the
devices' capabilities) takes the frames; the devices own the hardware. A
:class:`~dotshell.errors.DeviceError` from a move or a capture is a recoverable per-step
failure, retried ``scan.retries`` times before the scan fails (a lost device has already been
reconnected once by the rig, and a stopped one is never retried). Frames go to a writer thread
(writing overlaps the next capture) through a small bounded queue; a view is reported captured
only when all its frames are on disk (synced once per view), and every exit path — done,
stopped, failed, Ctrl-C — drains the queue first, so nothing captured is lost.

Setting the ``stop`` event (abort) stops moving devices at once (:meth:`Rig.stop`, from a small
watcher thread), as does Ctrl-C. Per view the run records the angle the stage read back and the
camera's frame metadata; at start the devices' identity and status (manifest ``devices``) and
their log lines (``events.jsonl``).
"""

from __future__ import annotations

import queue
import threading
import time
from pathlib import Path
from typing import Any, Callable, Mapping, TypeVar, cast

import numpy as np

from dotshell.coding import PatternFrame
from dotshell.devices import AngleReadback, ExposureControl, implements
from dotshell.errors import (DeviceError, DeviceLostError, DeviceStopped, FrameError,
                             ProfileError, RunError)
from dotshell.events import (EventBus, FrameCaptured, Message, ScanPaused, ScanResumed,
                             ViewCaptured)
from dotshell.run.frames import FrameStore
from dotshell.run.framecheck import FrameSpec
from dotshell.run.integrity import ViewIntegrity
from dotshell.run.lifecycle import signals_deferred
from dotshell.pipeline.engines import AcquisitionEngine, choose_engine
from dotshell.pipeline.pdi import Shot, plan_shots
from dotshell.pipeline.view_frames import ViewFrames
from dotshell.rig.assembly import Rig
from dotshell.rig.checks import refused_controls
from dotshell.run.layout import RunLayout
from dotshell.run.store import RunStore

T = TypeVar("T")


def with_retries(action: Callable[[], T], retries: int, what: str, bus: EventBus) -> T:
    """``action()``, tried again up to ``retries`` times when it raises DeviceError (a warning
    naming ``what`` per retry); the last failure is a DeviceError naming ``what``. A lost
    device (already reconnected once by the rig) and a stopped one are not retried."""
    attempts = retries + 1
    for attempt in range(1, attempts + 1):
        try:
            return action()
        except (DeviceLostError, DeviceStopped):
            raise
        except DeviceError as exc:
            if attempt == attempts:
                raise DeviceError(f"{what}: failed {attempts} times; last error: "
                                  f"{exc}") from None
            bus.warn(f"{what}: {exc} — retrying ({attempt}/{attempts - 1})")
    raise AssertionError("unreachable")


def check_frame(rig: Rig, spec: FrameSpec, frame: object, what: str) -> np.ndarray:
    """A frame just captured, checked against the run's frames (:mod:`dotshell.run.framecheck`)."""
    backend = rig.profile.required_role("camera")["backend"]
    return spec.check(frame, f"{what} from the camera ({backend})",
                      "Fix the camera's settings or its plugin; frames already written are "
                      "kept.")


class _NotAsProjected(Exception):
    """A captured view failed its integrity checks (raised after its frames were recorded)."""

    def __init__(self, verdict: ViewIntegrity) -> None:
        super().__init__("; ".join(verdict.problems))
        self.verdict = verdict


class FrameWriter:
    """Writes captured images to a :class:`RunStore` on a background thread, in order.

    Fringe frames are appended to their view's frame store (:mod:`dotshell.run.frames`) as they
    arrive and synced to the disk once per view, by :meth:`end_view`; other images
    (:meth:`put_path`) are written atomically one by one.
    """

    def __init__(self, store: RunStore, depth: int = 4) -> None:
        self.store = store
        self.queue: queue.Queue = queue.Queue(maxsize=depth)
        self.error: BaseException | None = None
        self._views: dict[int, FrameStore] = {}  # views being written
        #: fringe frames written per view: what a view's count in the manifest may say
        self.written: dict[int, int] = {}
        self.thread = threading.Thread(target=self._run, name="dotshell-frame-writer", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while True:
            item = self.queue.get()
            try:
                if item is None:
                    return
                if self.error is None or item[0] == "end":
                    self._write(*item)
            except OSError as exc:  # disk full, permissions, unplugged drive
                self.error = self.error or RunError(
                    f"could not write {item[-1]} to {self.store.root}: {exc}. Free disk space "
                    "or scan with --out on another drive; frames already written are kept.")
            except BaseException as exc:  # reported to the runner on its next call
                self.error = self.error or exc
            finally:
                self.queue.task_done()

    def _write(self, kind: str, *args: Any) -> None:
        if kind == "frame":
            view, index, image, _ = args
            if view not in self._views:
                self._views[view] = self.store.frames(view)
            self.store.check_room(self._views[view].path)
            self._views[view].append(index, image)
            self.written[view] = self.written.get(view, 0) + 1
        elif kind == "image":
            self.store.write_image(*args)
        elif kind == "sync":
            for frames in self._views.values():
                frames.sync()
        elif kind == "end":  # one view, or all (None)
            for view in [args[0]] if args[0] is not None else list(self._views):
                stack = self._views.pop(view, None)
                if stack is not None:
                    stack.close()

    def put(self, view: int, index: int, name: str, image: np.ndarray) -> None:
        """Queue a fringe frame of a view."""
        self.check()
        with signals_deferred():  # a put cut short by Ctrl-C would leave the writer asleep
            self.queue.put(("frame", view, index, image, f"frame {name!r} of view {view}"))

    def put_path(self, path: Path, image: np.ndarray, label: str) -> None:
        """Queue any captured image for ``path`` in the run; ``label`` names it in errors."""
        self.check()
        with signals_deferred():
            self.queue.put(("image", path, image, label))

    def sync(self) -> None:
        """Return when everything queued is written and the frames of open views are synced."""
        with signals_deferred():
            self.queue.put(("sync", "the frames of the open views"))
        self.queue.join()

    def end_view(self, view: int) -> None:
        """Return when every frame queued for ``view`` is written and synced to the disk (one
        fsync per view); the view's file is then complete."""
        with signals_deferred():
            self.queue.put(("end", view, f"the frames of view {view}"))
        self.queue.join()

    def check(self) -> None:
        if self.error is not None:
            raise self.error

    def close(self) -> None:
        """Finish every view still open and stop the thread."""
        with signals_deferred():
            self.queue.put(("end", None, "the frames of the open views"))
        self.queue.join()
        with signals_deferred():
            self.queue.put(None)
        self.thread.join()


class Acquisition:
    """Captures views of a scan into a :class:`RunStore`."""

    def __init__(self, rig: Rig, patterns: list[PatternFrame], store: RunStore,
                 scan: Mapping[str, Any], bus: EventBus, stop: threading.Event | None = None,
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
        self._device_lines: queue.SimpleQueue = queue.SimpleQueue()
        self._unlisten = rig.listen(lambda *line: self._device_lines.put(line))
        for line in rig.messages:  # logged while connecting, before this run listened
            self._device_lines.put(line)
        rig.where = {"run": str(store.root)}
        store.update_manifest(devices=rig.describe())
        self._closed = threading.Event()
        threading.Thread(target=self._stop_watch, name="dotshell-stop-watch", daemon=True).start()
        self.writer = FrameWriter(store)
        self.spec = FrameSpec.of_camera(rig.camera)
        if implements(rig.camera, ExposureControl):
            cast(ExposureControl, rig.camera).set_exposure(scan["exposure_ms"])
        for refusal in refused_controls(rig):
            bus.warn(refusal)
        self.engine: AcquisitionEngine = choose_engine(rig, patterns, self.shots, scan, bus,
                                                       self._retry)
        for role, policy in rig.policies.items():
            if policy.home == "before_scan":
                self.bus.info(f"homing the {role} before the scan")
                rig.home(role)
        self.flush_device_log()

    def _retry(self, action: Callable[[], T], what: str) -> T:
        """``action()`` under the scan's retry policy (:func:`with_retries`)."""
        return with_retries(action, self.scan["retries"], what, self.bus)

    def _stop_watch(self) -> None:
        """Stop moving devices as soon as the scan is asked to stop (abort from any thread)."""
        while not self._closed.is_set():
            if self.stop.wait(0.05):
                self.rig.stop()
                return

    def flush_device_log(self) -> None:
        """Publish the devices' log lines (from any thread) on the bus, from this thread."""
        while True:
            try:
                level, text, when = self._device_lines.get_nowait()
            except queue.Empty:
                return
            self.bus.emit(Message(level=level, text=text, time=when))

    def _move(self, view: int, angle_deg: float) -> dict[str, Any]:
        """Move the stage for a view (retried like captures); what the stage read back."""
        self.rig.where.update(view=view, angle_deg=angle_deg)
        with_retries(lambda: self.rig.stage.move_to(angle_deg), self.scan["retries"],
                     f"view {view}: stage move to {angle_deg:g}°", self.bus)
        reached: dict[str, Any] = {}
        if implements(self.rig.stage, AngleReadback):
            reached["angle_read_deg"] = float(cast(AngleReadback, self.rig.stage).read_angle())
        return reached

    def _wait_if_paused(self, view: int, index: int) -> bool:
        """Block while ``running`` is cleared (a pause between frames); False if stopped
        meanwhile. Pause time is not counted in the acquisition time."""
        if self.running is None or self.running.is_set():
            return True
        self.writer.sync()  # frames taken before the pause are on disk while we wait
        self.bus.emit(ScanPaused(view=view, index=index))
        t0 = time.perf_counter()
        while not self.running.wait(0.05):
            if self.stop.is_set():
                return False
        self.seconds -= time.perf_counter() - t0
        self.bus.emit(ScanResumed(view=view, index=index))
        return True

    def run_view(self, view: int, angle_deg: float) -> ViewFrames | None:
        """Capture all frames of one view (on disk as they come; returned as what the view's
        reconstruction needs of them, :class:`~dotshell.pipeline.view_frames.ViewFrames`);
        None if the scan was stopped midway (frames taken
        so far stay on disk and the view is marked incomplete). A view whose frames are not
        what was projected (:mod:`dotshell.run.integrity`) is named, its frames set aside
        (``frames/view_NNN.partial-K``, kept) and captured again, up to ``scan.retries`` times;
        a FrameError names the faults if it never passes."""
        attempts = self.scan["retries"] + 1
        for attempt in range(1, attempts + 1):
            try:
                return self._run_view_once(view, angle_deg, attempt)
            except _NotAsProjected as exc:
                problems = "; ".join(exc.verdict.problems[:3])
                if attempt == attempts:
                    raise FrameError(
                        f"view {view}: the frames are not what was projected after {attempts} "
                        f"captures ({problems}). Check the camera's trigger, buffering and "
                        "cable; frames are kept in frames/view_NNN.partial-K. Set "
                        "[scan] frame_checks = false only if the scene itself defeats the "
                        "checks.") from None
                self.bus.warn(f"view {view}: frames are not what was projected ({problems}); "
                              f"capturing the view again ({attempt}/{attempts - 1})")
                self._set_aside(view)
        raise AssertionError("unreachable")

    def _set_aside(self, view: int) -> None:
        """Move a failed capture of ``view`` out of the way (kept) before it is captured again."""
        from dotshell.run.frames import set_aside_partial  # the run's one way to do it

        set_aside_partial(self.store.root, view)
        self.writer.written[view] = 0
        self.store.mark_view(view, 0, False)

    def _check_integrity(self, view: int, frames: ViewFrames,
                         infos: list[dict[str, Any]]) -> ViewIntegrity | None:
        """The view's frames against what was projected; None when ``frame_checks`` is off."""
        if not self.scan.get("frame_checks", True) or len(frames) != len(self.shots):
            return None
        return frames.integrity(float((1 << self.spec.bit_depth) - 1), infos or None)

    def _run_view_once(self, view: int, angle_deg: float, attempt: int
                       ) -> ViewFrames | None:
        t0 = time.perf_counter()
        verdict: ViewIntegrity | None = None
        frames = ViewFrames(self.shots)  # what the view needs of its frames, as they come
        infos: list[dict[str, Any]] = []
        reached: dict[str, Any] = {}
        try:
            reached = self._move(view, angle_deg)
            self.flush_device_log()
            for i, shot in enumerate(self.shots):
                captured = self.engine.holds_frames()
                if (self.stop.is_set() and not captured) or not self._wait_if_paused(view, i):
                    return None
                raw, info = self.engine.frame(view, i)
                frame = check_frame(self.rig, self.spec, raw, f"view {view}, frame {shot.name!r}")
                if info is not None:
                    infos.append({"index": i, "name": shot.name, **info.to_dict()})
                self.writer.put(view, i, shot.name, frame)
                frames.add(frame)
                self.flush_device_log()
                self.bus.emit(FrameCaptured(view=view, index=i, name=shot.name))
            verdict = self._check_integrity(view, frames, infos)
        except DeviceStopped as exc:
            self.bus.warn(f"view {view}: {exc}")
            self.stop.set()
            return None
        except KeyboardInterrupt:
            self.rig.stop()
            raise
        finally:
            with signals_deferred():  # a stop arriving now is raised once the view is recorded
                self.writer.end_view(view)  # every frame taken is on disk before we go on
                written = self.writer.written.get(view, 0)  # on disk, not merely captured
                self.store.mark_view(view, written, written == len(self.shots) and
                                     (verdict is None or verdict.ok))
                self._record_view(view, reached, infos, verdict, attempt)
            self.flush_device_log()
            self.seconds += time.perf_counter() - t0
        self.writer.check()
        if verdict is not None and not verdict.ok:
            raise _NotAsProjected(verdict)
        self.bus.emit(ViewCaptured(view=view, angle_deg=angle_deg, n_frames=len(frames)))
        return frames

    def _record_view(self, view: int, reached: dict[str, Any], infos: list[dict[str, Any]],
                     verdict: ViewIntegrity | None = None, attempt: int = 1) -> None:
        """The angle read back and the frames' integrity (manifest) and the frames' metadata
        (``frame_info.json``)."""
        if infos:
            record_frame_info(self.store, view, infos)
        if reached or infos or verdict is not None:
            m = self.store.manifest
            m["views"][view].update(reached)
            if infos:
                m["views"][view]["frame_info"] = frame_info_path(view)
            if verdict is not None:
                m["views"][view]["integrity"] = {**verdict.to_dict(), "captures": attempt}
            self.store.write_json(RunLayout.MANIFEST, m)

    def close(self) -> None:
        """Stop the writer thread (after it wrote everything queued) and the stop watcher."""
        self._closed.set()
        self._unlisten()
        self.flush_device_log()
        self.writer.close()


def frame_info_path(view: int) -> str:
    """Where a view's frame metadata goes, relative to the run."""
    return RunLayout.frame_info(view)


def record_frame_info(store: RunStore, view: int, infos: list[dict[str, Any]]) -> Path:
    """Write one view's frame metadata (one dict per frame: index, name, timestamp_s,
    frame_id, exposure_ms, ...) next to its frames."""
    return store.write_json(frame_info_path(view), infos)
