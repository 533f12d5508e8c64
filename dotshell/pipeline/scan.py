"""Scans: capture every view (reconstructing each one while the next is captured), then the
rest of the processing steps; ``resume`` finishes an interrupted or failed scan (``reconstruct``,
which re-processes a run from its frames as a new generation, is in
:mod:`dotshell.pipeline.commands`).

Front ends call :func:`scan` and :func:`resume_run` and listen to the
:class:`EventBus`. The lifecycle (lock, status, reason) belongs to
:class:`dotshell.pipeline.engine.RunJob`; the steps after acquisition to
:func:`dotshell.pipeline.engine.process`.
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

from dotshell.runtime import hugepages
from dotshell.errors import CalibrationError, FrameError, RunError
from dotshell.run.framecheck import FrameSpec
from dotshell.events import EventBus, ScanFinished, ScanStarted, StepStarted, ViewCaptured, \
    ViewReconstructed
from dotshell.geometry.calibration import RigCalibration
from dotshell.geometry.opencv_io import load_any_calibration
from dotshell.pipeline.acquire import Acquisition
from dotshell.pipeline.engine import RunJob, process
from dotshell.pipeline.kernel_warmup import KernelWarmup
from dotshell.run.frames import set_aside_partial
from dotshell.run.generations import Generation, ProductStore
from dotshell.run.lifecycle import connected, describe_holder, lock_holder
from dotshell.pipeline.pdi import plan_shots
from dotshell.pipeline.steps import (PatternImages, make_coding, reconstruct_one_view,
                                     require_turntable_axis, view_angle)
from dotshell.pipeline.transillum import TransilluminationCapture
from dotshell.plugins import PluginManager
from dotshell.profile.loader import Profile, validate_profile
from dotshell.rig.assembly import Rig
from dotshell.run.layout import RunLayout
from dotshell.run.store import RunStore

#: What a scan makes: everything downstream of the calibration.
SCAN_TARGETS = ("calibration",)


@dataclass
class ScanResult:
    run_dir: Path
    status: str
    report: dict[str, Any]
    reason: str = ""


def _forward_to_plugins(bus: EventBus, pm: PluginManager, profile: Profile, run_dir: str):
    """Subscribe a bridge from bus events to the plugins' workflow hooks."""

    def forward(ev):
        if isinstance(ev, ScanStarted):
            warns = pm.notify("dotshell_scan_started", run_dir=ev.run_dir, profile=profile.data,
                              n_views=ev.n_views)
        elif isinstance(ev, ViewCaptured):
            warns = pm.notify("dotshell_view_captured", run_dir=run_dir, view=ev.view,
                              angle_deg=ev.angle_deg, n_frames=ev.n_frames)
        elif isinstance(ev, ViewReconstructed):
            warns = pm.notify("dotshell_view_reconstructed", run_dir=run_dir, view=ev.view,
                              n_points=ev.n_points)
        elif isinstance(ev, ScanFinished):
            warns = pm.notify("dotshell_scan_finished", run_dir=ev.run_dir, status=ev.status,
                              report=ev.summary)
        else:
            return
        for w in warns:
            bus.warn(w)

    return bus.subscribe(forward)


@contextmanager
def _stoppable_rig(profile: Profile, pm: PluginManager, rig: Rig | None) -> Iterator[Rig]:
    """The scan's rig, its stop registered before the first device connects: Ctrl-C, SIGTERM
    and SIGHUP stop every moving device while connecting and homing as well as during the
    scan. A rig the scan built is closed afterwards (also when connecting was interrupted);
    a caller's rig is connected if needed and left open for the caller."""
    with connected(Rig(profile, pm) if rig is None else rig, close=rig is None) as ready:
        yield ready


class ViewPipeline:
    """Reconstructs captured views on one worker thread while the next view is captured. At
    most one view waits; views wait and are reconstructed as their pattern images (made as
    the frames come, :class:`~dotshell.pipeline.view_frames.ViewFrames`: with PDI, half their
    frames), so memory holds the pattern images of the view being captured and of two others."""

    def __init__(self, store: RunStore, profile: Profile, coding: Any, calib: RigCalibration,
                 bus: EventBus, ready: Callable[[], None] | None = None) -> None:
        self.args = (profile, coding, calib, bus)
        #: called before each view's reconstruction: returns once the kernels are compiled
        #: (:class:`~dotshell.pipeline.kernel_warmup.KernelWarmup`), the capture going on
        self.ready = ready
        self.store = store
        self.pool = ThreadPoolExecutor(1, thread_name_prefix="dotshell-reconstruct")
        self.futures: dict[int, Future] = {}

    def submit(self, view: int, angle_deg: float, images: PatternImages) -> None:
        self._wait(keep_pending=1)  # first: the view it waits for lets go of its images
        self.futures[view] = self.pool.submit(self._reconstruct, view, angle_deg, images)

    def _reconstruct(self, view: int, angle_deg: float, images: PatternImages
                     ) -> dict[str, Any]:
        """One view, its maps' memory then given back (:func:`dotshell.runtime.hugepages.release`):
        a scan's reconstruction hides behind the capture, and until the next view the
        capture needs the memory more than the next decode needs it lent."""
        profile, coding, calib, bus = self.args
        try:
            if self.ready is not None:
                self.ready()
            return reconstruct_one_view(self.store, view, angle_deg, profile, coding, calib, bus,
                                        images=images)
        finally:
            hugepages.release()

    def _wait(self, keep_pending: int) -> None:
        """Block until at most ``keep_pending`` views are unfinished; raise the first failure."""
        while sum(not f.done() for f in self.futures.values()) > keep_pending:
            next(f for f in self.futures.values() if not f.done()).result()
        for f in self.futures.values():
            if f.done() and f.exception() is not None:
                raise f.exception()  # type: ignore[misc]

    def drain(self) -> None:
        """Wait until every submitted view is reconstructed (raises the first failure). The
        scan drains before a trans-illumination view: the simulated laser's view (~0.12 GB at
        full resolution, its FEM truth and open3d at the first one) and a view's
        reconstruction (~0.15 GB) together made the agar scan's peak (issue 33)."""
        self._wait(keep_pending=0)

    def results(self) -> dict[int, dict[str, Any]]:
        """Every view's record, once all are done (raises the first failure)."""
        self._wait(keep_pending=0)
        return {v: f.result() for v, f in self.futures.items()}

    def close(self) -> None:
        """Drop views not started yet; wait for the one in progress (its files stay partial
        in the unpublished generation)."""
        for f in self.futures.values():
            f.cancel()
        self.pool.shutdown(wait=True)


def scan(profile: Profile, pm: PluginManager, out_dir: Path | str = "runs",
         bus: EventBus | None = None, stop: threading.Event | None = None,
         calibration_file: str | None = None, running: threading.Event | None = None,
         rig: Rig | None = None) -> ScanResult:
    """Run a full scan; returns when done or stopped through ``stop`` (``status="aborted"``);
    raises on failure or Ctrl-C/SIGTERM (the run is then marked ``failed``/``aborted`` with
    the reason, and everything captured so far is kept).

    Clearing ``running`` pauses the acquisition before its next frame, setting it again
    resumes. ``rig``: use this rig (connected if needed, left open afterwards, e.g. a front
    end's live session) instead of opening the profile's devices for the scan alone.
    """
    bus = bus or EventBus()
    coding = make_coding(profile, pm)  # a bad coding or calibration is refused before a run
    calibration = calibration_file or profile.calibration_path()  # is made
    calib = load_any_calibration(calibration) if calibration is not None and rig is None else None
    store = RunStore.create(Path(out_dir), profile.name)

    def create() -> None:
        store.write_profile(profile.raw())
        store.init_manifest(profile.name, profile.angles_deg(), [])

    return _capture_and_process(store, profile, pm, bus, "scan", coding, stop, running, rig,
                                calibration_file, create, calib=calib)


def resume_run(run_dir: Path | str, pm: PluginManager, bus: EventBus | None = None,
               stop: threading.Event | None = None, running: threading.Event | None = None,
               rig: Rig | None = None, views: list[int] | None = None) -> ScanResult:
    """``dotshell resume RUN``: capture the views an interrupted, aborted or failed scan did not
    finish — same profile, same calibration, the stage back at each view's angle — then process
    the whole run into a new generation. Frames of an unfinished view are set aside in
    ``frames/view_NNN.partial-K`` (never deleted) before the view is captured again.
    ``views``: also capture these views again (``--view N``: a view whose frame stack was cut
    or deleted after the scan; a completed run included)."""
    bus = bus or EventBus()
    store = RunStore.open(Path(run_dir))
    recapture = _views_asked(store, views or [])
    status, _ = store.status()
    if status == "running":
        raise RunError(f"{store.root} is being written by "
                       f"{describe_holder(lock_holder(store.root) or {})}; it can be resumed "
                       "once that process has ended (`dotshell inspect RUN` shows it).")
    _refuse_damaged_views(store, recapture)
    if status == "completed" and not recapture:
        raise RunError(f"{store.root} is completed; nothing to resume. Re-process it with "
                       "`dotshell reconstruct RUN`.")
    profile = load_run_profile(store, pm)
    coding = make_coding(profile, pm)
    calib = None
    if store.path(RunLayout.CALIBRATION).is_file():
        calib = RigCalibration.load(store.path(RunLayout.CALIBRATION))  # checked before the job
    elif any(v["frames"] for v in store.manifest["views"]):
        raise RunError(f"{store.root} has frames but no calibration.json; restore the run's "
                       "calibration.json from a backup to resume it.")
    return _capture_and_process(store, profile, pm, bus, "resume", coding, stop, running, rig,
                                None, None, recapture, calib)


def _views_asked(store: RunStore, views: list[int]) -> frozenset[int]:
    n = len(store.manifest["views"])
    wrong = [v for v in views if not 0 <= v < n]
    if wrong:
        raise RunError(f"--view {wrong[0]}: {store.root} has views 0 to {n - 1} (the N of "
                       "frames/view_NNN.tif).")
    return frozenset(views)


def _refuse_damaged_views(store: RunStore, recapture: frozenset[int]) -> None:
    """A view recorded complete whose frames were cut or deleted since is named, with the way
    out, unless it is to be captured again."""
    from dotshell.run.frames import damaged_views

    damaged = [d for d in damaged_views(store.root, store.manifest) if d[0] not in recapture]
    if damaged:
        named = "; ".join(f"view {v} has {n} of its {rec} frames on disk" for v, n, rec in damaged)
        flags = " ".join(f"--view {v}" for v, _, _ in damaged)
        views = " ".join(str(v) for v, _, _ in damaged)
        raise RunError(f"{store.root}: {named} (its frame stack was cut or deleted after the "
                       f"scan). Re-capture it with `dotshell resume {store.root} {flags}` (the "
                       "rig set up as for the scan; the damaged frames are kept aside as "
                       "view_NNN.partial-K), restore the stack from a backup, or, if it cannot "
                       "be re-captured, mark it lost so the run completes from the other views: "
                       f"`dotshell lose-view {store.root} {views} --reason TEXT`.")


def _capture_and_process(store: RunStore, profile: Profile, pm: PluginManager, bus: EventBus,
                         command: str, coding: Any, stop: threading.Event | None,
                         running: threading.Event | None, rig: Rig | None,
                         calibration_file: str | None, create,
                         recapture: frozenset[int] = frozenset(),
                         calib: RigCalibration | None = None) -> ScanResult:
    """Acquire and process in a run job. ``calib``: the calibration the caller loaded (and
    so checked) before the job, used as is (the file is read once)."""
    unsubs = [bus.subscribe(lambda ev: store.append_event(ev.to_dict())),
              _forward_to_plugins(bus, pm, profile, str(store.root))]
    job = RunJob(store, command, bus, create)
    report: dict[str, Any] = {}
    try:
        with job:
            report = _acquire_then_process(job, profile, pm, coding, stop, running, rig,
                                           calibration_file, recapture, calib)
    finally:
        if job.status is not None:
            bus.emit(ScanFinished(status=job.status, run_dir=str(store.root),
                                  summary=_summary(report), reason=job.reason))
        for u in unsubs:
            u()
        store.close()
    return ScanResult(store.root, job.status or "failed", report, job.reason)


def _acquire_then_process(job: RunJob, profile: Profile, pm: PluginManager, coding: Any,
                          stop: threading.Event | None, running: threading.Event | None,
                          rig: Rig | None, calibration_file: str | None,
                          recapture: frozenset[int] = frozenset(),
                          loaded: RigCalibration | None = None) -> dict[str, Any]:
    store, bus = job.store, job.bus
    # a resumed run continues with its own calibration; one killed before it recorded any
    # (nothing was captured yet) starts as a new scan would
    resuming = job.command == "resume" and store.path(RunLayout.CALIBRATION).is_file()
    gen = Generation.start(store)
    job.generation = gen.number
    products = ProductStore(store, gen.dir)
    with _stoppable_rig(profile, pm, rig) as rig:
        if resuming:
            calib = loaded or RigCalibration.load(store.path(RunLayout.CALIBRATION))
        else:
            calib = loaded or rig.calibration(calibration_file)
            require_turntable_axis(calib, profile.angles_deg(), profile.source)
        spec = _check_devices(store, rig, calib, resuming)
        if not resuming:
            calib.save(store.path(RunLayout.CALIBRATION))
        kernels = KernelWarmup.start(store.root, profile.data, spec.bit_depth, pm)
        patterns = coding.patterns(rig.projector.resolution)
        shots = plan_shots(patterns, profile.scan)
        _record_sequence(store, shots, patterns, resuming)
        angles = profile.angles_deg()
        bus.emit(ScanStarted(run_dir=str(store.root), profile=profile.name,
                             n_views=len(angles), frames_per_view=len(shots)))
        acq = Acquisition(rig, patterns, store, profile.scan, bus, stop, running,
                          shots=shots)
        pipeline = ViewPipeline(products, profile, coding, calib, bus,
                                ready=lambda: kernels.wait(bus, stop))
        try:
            trans = _transillumination(rig, store, profile, acq, bus)
            todo = _views_to_capture(store, trans, recapture)
            bus.emit(StepStarted(step="acquire", total=len(todo) * len(shots)))
            for view, fringes in todo:
                angle = angles[view]
                if fringes:
                    set_aside_partial(store.root, view)
                    frames = acq.run_view(view, angle)
                    if frames is None:
                        job.finish("aborted", "aborted by the user")
                        bus.warn(f"scan stopped during view {view + 1} of {len(angles)}; frames "
                                 f"kept in {store.root}")
                        break
                else:
                    rig.stage.move_to(angle)
                if fringes and frames is not None:  # None: stopped, the loop has ended
                    pipeline.submit(view, view_angle(store.manifest["views"][view]),
                                    frames.images())
                    del frames  # the pipeline holds their pattern images until reconstructed
                if trans is not None and trans.covers(view):
                    pipeline.drain()  # the laser view is not traced beside a reconstruction
                    kernels.wait(bus, stop)  # the laser's FEM kernels
                    trans.run_view(view)
            last_frame_at = time.monotonic() if todo else None  # last frames stored
            reconstructed = pipeline.results()
        finally:
            acq.close()
            pipeline.close()
    if not any(v["complete"] for v in store.manifest["views"]) and job.status == "aborted":
        return {}
    options = {"reconstructed": reconstructed, "prewritten": {"views": gen.listing()},
               "timings": {"acquire": acq.seconds}, "last_frame_at": last_frame_at,
               "calibration": calib}
    return process(job, profile, pm, SCAN_TARGETS, options,
                   final_status=job.status or "completed", generation=gen)


def _check_devices(store: RunStore, rig: Rig, calib: RigCalibration, resuming: bool
                   ) -> FrameSpec:
    """The calibration fits the camera and projector, and a resumed run's camera gives the
    frames the run was captured with; a new run records what its frames are (``camera``).
    Returns the camera's frame format."""
    spec = FrameSpec.of_camera(rig.camera)
    for role, lens, size in (("camera", calib.camera, rig.camera.resolution),
                             ("projector", calib.projector, rig.projector.resolution)):
        if tuple(lens.size) != tuple(size):
            raise CalibrationError(
                f"{calib.source}: the calibration's {role} is {lens.width}x{lens.height} px but "
                f"the {role} ({rig.profile.required_role(role)['backend']}) is {size[0]}x{size[1]} px; "
                f"give the calibration of this {role} at this resolution (or set the {role}'s "
                "resolution to the calibrated one).")
    if not resuming:
        store.update_manifest(camera=spec.to_dict())
        return spec
    recorded = store.manifest.get("camera")
    if recorded is not None and FrameSpec.from_dict(recorded) != spec:
        was = FrameSpec.from_dict(recorded)
        raise FrameError(
            f"{store.root} was captured at {was.bit_depth} bit, {was.width}x{was.height} px, but "
            f"the camera ({rig.profile.required_role('camera')['backend']}) now reports {spec.bit_depth} "
            f"bit, {spec.width}x{spec.height} px: a resumed view must match the others. Set the "
            f"camera's bit_depth and resolution as they were (in {store.path('profile.toml')}).")
    return spec


def _record_sequence(store: RunStore, shots, patterns, resuming: bool) -> None:
    names = [s.name for s in shots]
    if resuming:
        if store.manifest["frame_names"] != names:
            raise RunError(f"{store.root}: the coding now gives the frames {names[:3]}... but "
                           f"the run was captured with {store.manifest['frame_names'][:3]}...; "
                           "resume with the plugins the run was made with.")
        return
    store.update_manifest(frame_names=names, shots=[s.to_dict() for s in shots],
                          pattern_names=[p.name for p in patterns])


def _views_to_capture(store: RunStore, trans: TransilluminationCapture | None,
                      recapture: frozenset[int] = frozenset()) -> list[tuple[int, bool]]:
    """(view, fringes needed) for every view that misses fringe or trans-illumination frames,
    and those of ``recapture`` (captured again whole); not those marked lost, unless asked."""
    from dotshell.run.lost import is_lost

    m = store.manifest
    done_trans = (m.get("transillumination") or {}).get("views", {})
    todo = []
    for v in m["views"]:
        needs_trans = trans is not None and trans.covers(v["index"]) and \
            done_trans.get(str(v["index"])) != trans.expected_names()
        again = v["index"] in recapture
        if is_lost(v) and not again:  # the operator gave it up (`dotshell lose-view`)
            continue
        if not v["complete"] or needs_trans or again:
            todo.append((v["index"], not v["complete"] or again))
    return todo


def _transillumination(rig: Rig, store: RunStore, profile: Profile, acq: Acquisition,
                       bus: EventBus) -> TransilluminationCapture | None:
    """The scan's trans-illumination step (flat field captured now, unless a resumed run
    already has it), or None if disabled."""
    t = profile.transillumination
    if not t.enabled:
        return None
    trans = TransilluminationCapture(rig, store, t, profile.scan, acq.writer, bus,
                                     profile.base_dir)
    entry = store.manifest.get("transillumination")
    if entry is None:
        store.update_manifest(transillumination=trans.manifest_entry())
    if entry is None or (entry.get("flat_field") is None and t.flat_field != "none"):
        trans.capture_flat_field()
    return trans


def load_run_profile(store: RunStore, pm: PluginManager) -> Profile:
    """The exact profile a run was made with."""
    return validate_profile(store.read_profile(), pm, str(store.path(RunLayout.PROFILE)),
                            store.root)


def _summary(report: dict[str, Any]) -> dict[str, Any]:
    out = {"points": report.get("cloud", {}).get("points", 0)}
    v = report.get("validation") or {}
    for k in ("mean_rel_error_pct", "std_rel_error_pct", "coverage_pct"):
        if k in v:
            out[k] = v[k]
    return out
