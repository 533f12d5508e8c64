"""The scan workflow: profile → rig → acquire → reconstruct per view → merge → validate →
previews, and re-processing of a finished run from its frames on disk.

Front ends call :func:`scan` and :func:`reconstruct_run` and listen to the :class:`EventBus`.
"""

from __future__ import annotations

import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from dotshell.errors import ReconstructionError, RunError
from dotshell.events import (EventBus, ScanFinished, ScanStarted, StepProgress, StepStarted,
                             ViewCaptured, ViewReconstructed)
from dotshell.geometry.calibration import RigCalibration
from dotshell.pipeline.acquire import Acquisition
from dotshell.pipeline.pdi import combine, plan_shots, shots_from_manifest
from dotshell.pipeline.reconstruct import ViewCloud, reconstruct_view
from dotshell.pipeline.transillum import TransilluminationCapture
from dotshell.pipeline.validate import cylinder_report
from dotshell.plugins import PluginManager
from dotshell.ply import write_ply
from dotshell.profile import Profile, validate_profile
from dotshell.rig import Rig
from dotshell.store import RunStore


@dataclass
class ScanResult:
    run_dir: Path
    status: str
    report: dict[str, Any]


def _forward_to_plugins(bus: EventBus, pm: PluginManager, profile: Profile):
    """Subscribe a bridge from bus events to the plugins' workflow hooks."""

    def forward(ev):
        if isinstance(ev, ScanStarted):
            warns = pm.notify("dotshell_scan_started", run_dir=ev.run_dir, profile=profile.data,
                              n_views=ev.n_views)
        elif isinstance(ev, ViewCaptured):
            warns = pm.notify("dotshell_view_captured", run_dir=run_dir[0], view=ev.view,
                              angle_deg=ev.angle_deg, n_frames=ev.n_frames)
        elif isinstance(ev, ViewReconstructed):
            warns = pm.notify("dotshell_view_reconstructed", run_dir=run_dir[0], view=ev.view,
                              n_points=ev.n_points)
        elif isinstance(ev, ScanFinished):
            warns = pm.notify("dotshell_scan_finished", run_dir=ev.run_dir, status=ev.status,
                              report=ev.summary)
        else:
            return
        for w in warns:
            bus.warn(w)

    run_dir = [""]

    def track(ev):
        if isinstance(ev, ScanStarted):
            run_dir[0] = ev.run_dir

    bus.subscribe(track)
    return bus.subscribe(forward)


def _make_coding(profile: Profile, pm: PluginManager):
    c = profile.role("coding")
    return pm.create("coding", c["backend"], c["settings"], None, profile.source)


def _slim(vc: ViewCloud, profile: Profile) -> ViewCloud:
    """Drop per-pixel maps no later step needs (all but the preview view's), ~10 MB a view."""
    vc.pixels = None
    if vc.view != profile.data["outputs"]["preview_view"]:
        vc.correspondence = None
    return vc


def _store_view(store: RunStore, vc: ViewCloud, bus: EventBus) -> None:
    write_ply(store.path("views", f"view_{vc.view:03d}.ply"), vc.points)
    bus.emit(ViewReconstructed(view=vc.view, n_points=len(vc.points),
                               decoded_pixels=int(vc.stats.get("decoded", 0))))


@contextmanager
def _kept_open(rig: Rig) -> Iterator[Rig]:
    """A caller's rig: connected for the scan and left open for the caller."""
    rig.connect()
    yield rig


def scan(profile: Profile, pm: PluginManager, out_dir: Path | str = "runs",
         bus: EventBus | None = None, stop: threading.Event | None = None,
         calibration_file: str | None = None, running: threading.Event | None = None,
         rig: Rig | None = None) -> ScanResult:
    """Run a full scan; returns when done, stopped (``status="aborted"``) or failed (raises).

    Frames are on disk as they arrive; on any failure the run is marked ``failed`` (or
    ``aborted`` on Ctrl-C) and everything captured so far is kept. Clearing ``running``
    pauses the acquisition before its next frame, setting it again resumes. ``rig``: use this
    rig (connected if needed, left open afterwards, e.g. a front end's live session) instead
    of opening the profile's devices for the scan alone.
    """
    bus = bus or EventBus()
    coding = _make_coding(profile, pm)
    store = RunStore.create(Path(out_dir), profile.name)
    unsubs = [bus.subscribe(lambda ev: store.append_event(ev.to_dict())),
              _forward_to_plugins(bus, pm, profile)]
    status, report = "failed", {}
    try:
        store.write_profile(profile.raw())
        angles = profile.angles_deg()
        store.init_manifest(profile.name, angles, [])
        with (Rig(profile, pm) if rig is None else _kept_open(rig)) as rig:
            calib = rig.calibration(calibration_file)
            calib.save(store.path("calibration.json"))
            patterns = coding.patterns(rig.projector.resolution)
            shots = plan_shots(patterns, profile.data["scan"])
            store.update_manifest(frame_names=[s.name for s in shots],
                                  shots=[s.to_dict() for s in shots],
                                  pattern_names=[p.name for p in patterns])
            bus.emit(ScanStarted(run_dir=str(store.root), profile=profile.name,
                                 n_views=len(angles), frames_per_view=len(shots)))
            bus.emit(StepStarted(step="acquire", total=len(angles) * len(shots)))
            acq = Acquisition(rig, patterns, store, profile.data["scan"], bus, stop, running,
                              shots=shots)
            clouds = []
            try:
                trans = _transillumination(rig, store, profile, acq, bus)
                for view, angle in enumerate(angles):
                    frames = acq.run_view(view, angle)
                    if frames is None:
                        status = "aborted"
                        bus.warn(f"scan stopped during view {view}; frames kept in {store.root}")
                        break
                    if trans is not None and trans.covers(view):
                        trans.run_view(view)
                    vc = reconstruct_view(view, angle, combine(frames, shots), coding, calib,
                                          profile.data["processing"])
                    del frames  # not held while the next view is captured (110 MB at 1280×1024)
                    _store_view(store, vc, bus)
                    clouds.append(_slim(vc, profile))
                else:
                    status = "completed"
            finally:
                acq.close()
        if clouds:
            report = finish(store, profile, pm, calib, clouds, bus, {"acquire": acq.seconds})
        report["status"] = status
        store.write_json("report.json", report)
    except KeyboardInterrupt:
        status = "aborted"
        raise
    finally:
        if store.path("manifest.json").is_file():
            store.update_manifest(status=status)
        bus.emit(ScanFinished(status=status, run_dir=str(store.root), summary=_summary(report)))
        for u in unsubs:
            u()
        store.close()
    return ScanResult(store.root, status, report)


def _transillumination(rig: Rig, store: RunStore, profile: Profile, acq: Acquisition,
                       bus: EventBus) -> TransilluminationCapture | None:
    """The scan's trans-illumination step (flat field captured now), or None if disabled."""
    t = profile.data["transillumination"]
    if not t["enabled"]:
        return None
    trans = TransilluminationCapture(rig, store, t, profile.data["scan"], acq.writer, bus,
                                     profile.base_dir)
    store.update_manifest(transillumination=trans.manifest_entry())
    trans.capture_flat_field()
    return trans


def load_run_profile(store: RunStore, pm: PluginManager) -> Profile:
    """The exact profile a run was made with."""
    import tomllib

    p = store.path("profile.toml")
    try:
        raw = tomllib.loads(p.read_text())
    except FileNotFoundError:
        raise RunError(f"{p} is missing; this run cannot be re-processed.") from None
    return validate_profile(raw, pm, str(p), store.root)


@contextmanager
def reopened_run(run_dir: Path | str, pm: PluginManager,
                 bus: EventBus) -> Iterator[tuple[RunStore, Profile]]:
    """An existing run opened for re-processing, with the exact profile it was made with; the
    bus's events go to its ``events.jsonl`` until the block ends."""
    store = RunStore.open(Path(run_dir))
    unsub = bus.subscribe(lambda ev: store.append_event(ev.to_dict()))
    try:
        yield store, load_run_profile(store, pm)
    finally:
        unsub()
        store.close()


def reconstruct_run(run_dir: Path | str, pm: PluginManager, bus: EventBus | None = None,
                    calibration_file: str | None = None) -> ScanResult:
    """Re-run processing of a run from its frames on disk (views not fully captured are
    skipped with a warning). Overwrites the run's views, cloud, report and previews."""
    bus = bus or EventBus()
    with reopened_run(run_dir, pm, bus) as (store, profile):
        calib = RigCalibration.load(calibration_file or store.path("calibration.json"))
        if calibration_file:
            calib.save(store.path("calibration.json"))
        coding = _make_coding(profile, pm)
        manifest = store.manifest
        shots = shots_from_manifest(manifest)
        views = manifest["views"]
        bus.emit(StepStarted(step="reconstruct", total=len(views)))
        clouds = []
        for v in views:
            if not v["complete"]:
                bus.warn(f"view {v['index']} has {v['frames']} of "
                         f"{len(manifest['frame_names'])} frames; skipped")
                continue
            frames = combine(store.read_frames(v["index"]), shots)
            vc = reconstruct_view(v["index"], v["angle_deg"], frames, coding, calib,
                                  profile.data["processing"])
            del frames  # not held while the next view is read
            _store_view(store, vc, bus)
            clouds.append(_slim(vc, profile))
            bus.emit(StepProgress(step="reconstruct", done=v["index"] + 1, total=len(views)))
        report = finish(store, profile, pm, calib, clouds, bus, {})
        report["status"] = manifest.get("status", "unknown")
        report["reprocessed"] = True
        store.write_json("report.json", report)
    return ScanResult(store.root, report["status"], report)


def finish(store: RunStore, profile: Profile, pm: PluginManager, calib: RigCalibration,
           clouds: list[ViewCloud], bus: EventBus, timings: dict[str, float]) -> dict[str, Any]:
    """Merge views into ``cloud.ply``, validate, render previews; return the report."""
    timings = dict(timings)
    timings["decode"] = sum(c.seconds.get("decode", 0.0) for c in clouds)
    timings["triangulate"] = sum(c.seconds.get("triangulate", 0.0) for c in clouds)
    bus.emit(StepStarted(step="merge", total=len(clouds)))
    t0 = time.perf_counter()
    if not clouds or sum(len(c.points) for c in clouds) == 0:
        raise ReconstructionError(
            f"{store.root}: no view produced points inside the region of interest. Check the "
            "previews (is the sample lit and in focus?), the calibration and [processing.roi].")
    points = np.concatenate([c.points for c in clouds])
    view_ids = np.concatenate([np.full(len(c.points), c.view, np.float32) for c in clouds])
    write_ply(store.path("cloud.ply"), points, view=view_ids)
    timings["merge"] = time.perf_counter() - t0
    report: dict[str, Any] = {
        "profile": profile.name,
        "calibration": calib.source,
        "views": [{"view": c.view, "angle_deg": c.angle_deg, **c.stats} for c in clouds],
        "cloud": {"path": "cloud.ply", "points": int(len(points))},
    }
    v = profile.data["validation"]
    t0 = time.perf_counter()
    if v["shape"] == "cylinder":
        bus.emit(StepStarted(step="validate"))
        report["validation"] = cylinder_report(points, calib, v, profile.data["processing"]["roi"])
    timings["validate"] = time.perf_counter() - t0
    if profile.data["outputs"]["previews"]:
        from dotshell.render import render_previews

        bus.emit(StepStarted(step="previews"))
        t0 = time.perf_counter()
        report["previews"] = render_previews(store, clouds, points, profile, calib, bus)
        timings["previews"] = time.perf_counter() - t0
    if profile.data["mesh"]["after_scan"]:  # surface + volume before the exporters use them
        from dotshell.pipeline.mesh import mesh_stage

        t0 = time.perf_counter()
        report["mesh"] = mesh_stage(store, profile, pm, bus)
        timings["mesh"] = time.perf_counter() - t0
    if _normalize_after(store, profile):
        from dotshell.pipeline.normalize import normalize_stage

        t0 = time.perf_counter()
        report["normalize"] = normalize_stage(store, profile, pm, bus)
        timings["normalize"] = time.perf_counter() - t0
    if profile.data["export"]:
        t0 = time.perf_counter()
        report["exports"] = run_exporters(store, profile, pm, bus)
        timings["export"] = time.perf_counter() - t0
    report["timings_s"] = {k: round(s, 3) for k, s in timings.items()}
    return report


def _normalize_after(store: RunStore, profile: Profile) -> bool:
    """Normalize at the end of processing: trans-illumination frames exist, a surface was
    meshed now, and the profile asks for it."""
    entry = store.manifest.get("transillumination") or {}
    return bool(entry.get("views")) and profile.data["mesh"]["after_scan"] \
        and profile.data["normalize"]["after_scan"]


def run_exporters(store: RunStore, profile: Profile, pm: PluginManager, bus: EventBus) -> dict[str, list[str]]:
    """Run the profile's ``[export.NAME]`` exporters; returns the files each wrote."""
    out = {}
    for name, settings in profile.data["export"].items():
        bus.emit(StepStarted(step=f"export {name}"))
        exporter = pm.create("exporter", name, settings, None, profile.source)
        paths = exporter.export(store.root)
        out[name] = [str(Path(p).relative_to(store.root)) for p in paths]
    return out


def _summary(report: dict[str, Any]) -> dict[str, Any]:
    out = {"points": report.get("cloud", {}).get("points", 0)}
    v = report.get("validation") or {}
    for k in ("mean_rel_error_pct", "std_rel_error_pct", "coverage_pct"):
        if k in v:
            out[k] = v[k]
    return out
