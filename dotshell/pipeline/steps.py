"""The processing steps of a run, each a small object: its name (= the product it writes), the
products it reads, and ``run(ctx)`` returning its ``report.json`` sections.

::

    calibration ─► views ─► cloud ─┬─► validation
                                   ├─► previews
                                   └─► mesh ─┬─► normalize
                                             ├─► exports   (also reads cloud)
                                             └─► forward

Steps read the run's capture (frames, manifest) and earlier products through a
:class:`~dotshell.run.generations.ProductStore` and write into the job's generation;
:mod:`dotshell.pipeline.engine` decides which run, in this order, and publishes the result.
The per-view reconstruction (:func:`reconstruct_one_view`) is the unit a scan runs while the
next view is captured and a batch schedules on its workers.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np

from dotshell.runtime import hugepages
from dotshell.errors import CalibrationError, ReconstructionError, RunError
from dotshell.events import EventBus, StepProgress, StepStarted, ViewReconstructed
from dotshell.run.framecheck import FrameSpec
from dotshell.run.lost import is_lost, lost_views, usable
from dotshell.geometry.calibration import RigCalibration
from dotshell.geometry.opencv_io import load_any_calibration
from dotshell.pipeline.pdi import combine, shots_from_manifest
from dotshell.pipeline.view_frames import PatternImages
from dotshell.plugins import PluginManager
from dotshell.run.layout import RunLayout
from dotshell.run.ply import map_ply, ply_buffer, point_count, read_ply, write_ply
from dotshell.profile.loader import Profile
from dotshell.run.store import RunStore, atomic_write_bytes, atomic_write_text, dumps
from dotshell.pipeline.decode_quality import quality_fields

if TYPE_CHECKING:
    from dotshell.pipeline.reconstruct import ViewCloud


@dataclass
class StepContext:
    """What a step may use. ``store`` reads the capture and writes this generation's products;
    ``options`` holds the command's choices (node distance, normalizer, calibration file...)."""

    store: RunStore
    profile: Profile
    pm: PluginManager
    bus: EventBus
    options: dict[str, Any] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    #: called before the first view is reconstructed, with the context and that view's index
    #: (the engine's: :func:`dotshell.pipeline.kernel_warmup.kernels_before_views`)
    before_views: Callable[[StepContext, int], None] | None = None
    #: the calibration once loaded (by the calibration step or on first use); steps reuse it
    _calib: RigCalibration | None = None
    #: the merged cloud as ``cloud.ply`` holds it ((N, 3) float32, mm), kept by the merge for
    #: the validation and previews (reading the 5.5 M-point file again cost ~0.5 s each) and
    #: let go when the mesh step starts
    cloud: np.ndarray | None = None

    @property
    def calibration(self) -> RigCalibration:
        """The calibration of this generation (``calibration.json`` in it)."""
        if self._calib is None:
            self._calib = RigCalibration.load(self.store.path(RunLayout.CALIBRATION))
        return self._calib


@dataclass(frozen=True)
class Step:
    name: str
    reads: tuple[str, ...]
    run: Callable[[StepContext], dict[str, Any]]
    #: whether the step belongs in a run made with this profile (when not asked for directly)
    wanted: Callable[[StepContext, set[str]], bool] = lambda ctx, base: True
    #: imports what the step needs (seconds of CPU); run in the background while the step
    #: that makes its last input runs (:func:`import_ahead`)
    imports: Callable[[], None] | None = None


def make_coding(profile: Profile, pm: PluginManager):
    c = profile.required_role("coding")
    return pm.create("coding", c["backend"], c["settings"], None, profile.source)


# ---- calibration ---------------------------------------------------------------------------

def calibration_step(ctx: StepContext) -> dict[str, Any]:
    """This generation's calibration: the command's ``--calibration`` file (validated before
    anything is written) or the one the run was captured with; option ``calibration``: that
    calibration, already loaded by the command."""
    calib = ctx.options.get("calibration")
    if calib is None:
        source = ctx.options.get("calibration_file") or ctx.store.path("..", "..",
                                                                        RunLayout.CALIBRATION)
        calib = load_any_calibration(source)  # a user's file may be an OpenCV .yml/.xml
    calib.save(ctx.store.path(RunLayout.CALIBRATION))
    ctx._calib = calib
    return {"calibration": calib.source}


def require_turntable_axis(calib: RigCalibration, angles_deg: Sequence[float],
                           where: str) -> None:
    """Views at several stage angles are merged about the turntable axis: refuse a calibration
    whose axis was never measured (an OpenCV file, a solve without turntable frames)."""
    if not calib.axis_measured and len({round(a, 6) for a in angles_deg}) > 1:
        raise CalibrationError(
            f"{where}: calibration {calib.source} has no measured turntable axis, but the "
            f"views are at {len(set(angles_deg))} stage angles and are merged about it. Solve "
            "the axis with `dotshell calibrate` and turntable frames, or scan one view "
            "(--set scan.views=1).")


# ---- views ---------------------------------------------------------------------------------

def store_view(store: RunStore, vc: ViewCloud, first_frame: np.ndarray | None,
               profile: Profile, calib: RigCalibration, bus: EventBus) -> dict[str, Any]:
    """Write one reconstructed view (``views/view_NNN.ply`` + ``.json``; frame and column
    previews for the profile's preview view) and return its report record."""
    write_ply(store.path(RunLayout.view_cloud(vc.view)), vc.points)
    record: dict[str, Any] = {"view": vc.view, "angle_deg": vc.angle_deg, **vc.stats}
    if vc.quality:  # decoded share and neighbour reversals (dotshell.pipeline.decode_quality)
        record["quality"] = vc.quality
    integrity = getattr(store, "run", store).manifest["views"][vc.view].get("integrity")
    if integrity is not None:  # the capture's frame checks (dotshell.run.integrity)
        record["integrity"] = integrity
    out = profile.outputs
    if out.previews and vc.view == out.preview_view and vc.correspondence is not None:
        from dotshell.render.previews import column_map_preview, frame_preview

        store.path(RunLayout.PREVIEWS).mkdir(parents=True, exist_ok=True)
        columns = store.path(RunLayout.view_preview("columns", vc.view))
        previews = {"columns": column_map_preview(vc.correspondence.column,
                                                  vc.correspondence.valid, calib.projector.width,
                                                  columns)}
        if first_frame is not None:
            previews["frame"] = frame_preview(first_frame,
                                              store.path(RunLayout.view_preview("frame", vc.view)))
        record["previews"] = {k: str(Path(p).relative_to(store.root)) for k, p in previews.items()}
    atomic_write_text(store.path(RunLayout.view_record(vc.view)),
                      dumps({**record, "seconds": {k: round(s, 4) for k, s in vc.seconds.items()}}))
    bus.emit(ViewReconstructed(view=vc.view, n_points=len(vc.points),
                               decoded_pixels=int(vc.stats.get("decoded", 0)),
                               **quality_fields(vc.stats, vc.quality)))
    return record


def reconstruct_one_view(store: RunStore, view: int, angle_deg: float, profile: Profile,
                         coding: Any, calib: RigCalibration, bus: EventBus,
                         frames: Sequence[np.ndarray] | np.ndarray | None = None,
                         images: PatternImages | None = None) -> dict[str, Any]:
    """Decode and triangulate one view (its :func:`pattern_images` or frames given, else
    read from the run) into its products; returns its report record."""
    # here, not at the top: the decoding and triangulation (numba, 0.5-1 s to import) load with
    # the first view (a scan captures the next view meanwhile), not in a batch's client process
    # or in the commands that never reconstruct
    from dotshell.pipeline.reconstruct import reconstruct_view

    if images is None:
        images = pattern_images(store, stored_frames(store, view, calib) if frames is None
                                else frames)
    patterns, first_frame = images
    vc = reconstruct_view(view, angle_deg, patterns, coding, calib, profile.processing)
    return store_view(store, vc, first_frame, profile, calib, bus)


def pattern_images(store: RunStore, frames: Sequence[np.ndarray] | np.ndarray) -> PatternImages:
    """A view's frames in the run's shot order → (one image per pattern, the first frame):
    with PDI the exact ``|I∥ − I⊥|`` of each pair, half the frames' memory (a full-resolution
    agar view: 42 images of 2.5 MiB instead of 84 frames; issue 33)."""
    patterns = combine(frames, shots_from_manifest(store.manifest))
    return patterns, (frames[0] if len(frames) else None)


def stored_frames(store: RunStore, view: int, calib: RigCalibration,
                  out: np.ndarray | None = None) -> np.ndarray:
    """A view's frames from the run's files, each checked against the run's frames (the
    manifest's ``camera``; for runs made before it was recorded, the calibration's camera size
    and the depth of the view's first frame). ``out``: the previous view's frames, read over
    when the same size (:meth:`~dotshell.run.frames.FrameStore.read_all`)."""
    spec = stored_frame_spec(store, view, calib)
    root = store.run_root
    return store.read_frames(view, spec, "Restore the run's frames from a backup, re-capture "
                             f"the view (`dotshell resume {root} --view {view}`), or mark it "
                             f"lost (`dotshell lose-view {root} {view} --reason TEXT`).", out)


def stored_frame_spec(store: RunStore, view: int, calib: RigCalibration) -> FrameSpec:
    """The run's frames: the manifest's ``camera``, or for runs made before it was recorded,
    the calibration's camera size and the depth of ``view``'s first frame."""
    recorded = store.manifest.get("camera")
    if recorded is not None:
        return FrameSpec.from_dict(recorded)
    first = store.frames(view).read_one(0)
    return FrameSpec(*calib.camera.size, 8 if first.dtype == np.uint8 else 16)


def view_angle(view: dict[str, Any]) -> float:
    """The stage angle a view was captured at (degrees): the one read back from the stage
    when it could tell, else the one commanded."""
    return float(view.get("angle_read_deg", view["angle_deg"]))


def complete_views(store: RunStore) -> list[dict[str, Any]]:
    """The views processing reads: captured whole and not marked lost."""
    return [v for v in store.manifest["views"] if usable(v)]


def views_step(ctx: StepContext) -> dict[str, Any]:
    store, manifest = ctx.store, ctx.store.manifest
    views = manifest["views"]
    done: dict[int, dict[str, Any]] = ctx.options.get("reconstructed", {})
    if not any(usable(v) for v in views):
        n_lost = sum(is_lost(v) for v in views)
        raise ReconstructionError(
            f"no view of {store.run_root} is completely captured ({len(views)} views, "
            f"{sum(v['frames'] for v in views)} frames on disk" +
            (f", {n_lost} marked lost" if n_lost else "") + "): there is nothing to "
            f"reconstruct. Capture the missing views with `dotshell resume {store.run_root}`.")
    coding = None
    frames = None  # one view's frames at a time, read over the previous view's (same array)
    ctx.bus.emit(StepStarted(step="reconstruct", total=len(views)))
    for n, v in enumerate(views, 1):
        if is_lost(v):
            ctx.bus.info(f"view {v['index']} is marked lost ({v['lost']['reason']}); skipped")
            continue
        if not v.get("complete"):
            ctx.bus.warn(f"view {v['index'] + 1} of {len(views)} has {v['frames']} of "
                         f"{len(manifest['frame_names'])} frames; skipped")
            continue
        if v["index"] not in done:
            if coding is None:  # the first view to reconstruct: its kernels ready first
                coding = make_coding(ctx.profile, ctx.pm)
                if ctx.before_views is not None:
                    ctx.before_views(ctx, v["index"])
            frames = stored_frames(store, v["index"], ctx.calibration, frames)
            done[v["index"]] = reconstruct_one_view(store, v["index"], view_angle(v),
                                                    ctx.profile, coding, ctx.calibration, ctx.bus,
                                                    frames)
        ctx.bus.emit(StepProgress(step="reconstruct", done=n, total=len(views)))
    hugepages.release()  # the views' maps are freed; the later steps need none of them
    records = [done[i] for i in sorted(done)]
    seconds = [read_view_record(store, r["view"]).get("seconds", {}) for r in records]
    ctx.timings["decode"] = sum(s.get("decode", 0.0) for s in seconds)
    ctx.timings["triangulate"] = sum(s.get("triangulate", 0.0) for s in seconds)
    ctx.timings["quality"] = sum(s.get("quality", 0.0) for s in seconds)
    lost = lost_views(manifest)
    return {"views": records, **({"lost_views": lost} if lost else {})}


def read_view_record(store: RunStore, view: int) -> dict[str, Any]:
    p = store.path(RunLayout.view_record(view))
    try:
        return json.loads(p.read_text())
    except (OSError, ValueError) as exc:
        raise RunError(f"{p} is missing or damaged ({exc}); re-process the run with "
                       "`dotshell reconstruct RUN`.") from None


# ---- cloud, validation, previews -----------------------------------------------------------

def stored_views(store: RunStore) -> list[int]:
    return sorted(RunLayout.view_index(p.stem)
                  for p in store.path(RunLayout.VIEWS).glob(f"{RunLayout.VIEW_GLOB}.ply"))


def cloud_step(ctx: StepContext) -> dict[str, Any]:
    ctx.bus.emit(StepStarted(step="merge"))
    views = stored_views(ctx.store)
    # the views' files mapped, copied once into the merged file's bytes (float32 as stored:
    # the same values), which are written from there and which the later steps read as the
    # cloud (a float32 view of its columns): no list of parts, no concatenated copy (the agar
    # scan's 8.3 M points: 133 MB, where parts, copy, view ids and the file's bytes took
    # ~0.4 GB; issue 33)
    paths = [ctx.store.path(RunLayout.view_cloud(v)) for v in views]
    counts = [point_count(p) for p in paths]
    n = sum(counts)
    if n == 0:
        raise _no_points(ctx, views)
    data, records = ply_buffer(n, ["view"])
    start = 0
    for view, path, count in zip(views, paths, counts):
        records[start:start + count, :3] = map_ply(path)[0]
        records[start:start + count, 3] = view
        start += count
    atomic_write_bytes(ctx.store.path(RunLayout.CLOUD), data.data)  # no copy
    points = records[:, :3]
    last_frame_at = ctx.options.get("last_frame_at")
    if last_frame_at is not None:  # a scan: the latency from its last stored frame (s)
        ctx.timings["last_frame_to_cloud"] = time.monotonic() - last_frame_at
    ctx.cloud = points
    return {"cloud": {"path": RunLayout.CLOUD, "points": int(n)}}


def pixel_totals(records: Sequence[dict[str, Any]]) -> dict[str, int]:
    """Per-reason pixel counts summed over views (ints only)."""
    totals: dict[str, int] = {}
    for r in records:
        for k, v in r.items():
            if isinstance(v, int) and not isinstance(v, bool) and k != "view":
                totals[k] = totals.get(k, 0) + v
    return totals


def _no_points(ctx: StepContext, views: list[int]) -> ReconstructionError:
    """Why a run gave no point: the decoder's or triangulation's largest loss and its fix, or
    the region of interest when points were made but all fell outside it."""
    from dotshell.pipeline.reconstruct import no_points_error

    where = f"{ctx.store.run_root} ({len(views)} views reconstructed)"
    totals = pixel_totals([read_view_record(ctx.store, v) for v in views])
    if totals.get("triangulated", 0) == 0:
        has_rows = totals.get("refined_row", 0) > 0 or totals.get("row_rejected", 0) > 0
        return no_points_error(where, totals, ctx.calibration, has_rows,
                               ctx.profile.processing.min_ray_angle_deg)
    return ReconstructionError(
        f"{where}: {totals['triangulated']} pixels were triangulated but no point is left: "
        f"{totals.get('speckle', 0)} removed as speckle, {totals.get('outside_roi', 0)} outside "
        "the region of interest. Check [processing.roi] (radius_mm, z_min_mm, z_max_mm) against "
        "the sample's size and the calibration's turntable axis.")


def load_cloud(ctx: StepContext) -> np.ndarray:
    """The merged cloud (N, 3) in mm: float32 as the merge left it in this process (a view of
    the columns of ``cloud.ply``'s bytes), else
    ``cloud.ply`` read as float64 (the same values; the steps' arithmetic is float64)."""
    if ctx.cloud is not None:
        return ctx.cloud
    return read_ply(ctx.store.path(RunLayout.CLOUD))[0]


def validation_step(ctx: StepContext) -> dict[str, Any]:
    from dotshell.pipeline.validate import cylinder_report

    ctx.bus.emit(StepStarted(step="validate"))
    return {"validation": cylinder_report(load_cloud(ctx), ctx.calibration,
                                          ctx.profile.validation, ctx.profile.processing.roi)}


def previews_step(ctx: StepContext) -> dict[str, Any]:
    from dotshell.render.previews import cloud_previews

    ctx.bus.emit(StepStarted(step="previews"))
    out: dict[str, Any] = {}
    for v in stored_views(ctx.store):
        out.update(read_view_record(ctx.store, v).get("previews") or {})
    if not out:
        ctx.bus.warn(f"frame previews skipped: view {ctx.profile.outputs.preview_view}"
                     " ([outputs] preview_view) was not reconstructed")
    out.update(cloud_previews(ctx.store, load_cloud(ctx), ctx.profile, ctx.bus))
    return {"previews": out}


# ---- mesh, normalize, exports, forward -----------------------------------------------------

def mesh_step(ctx: StepContext) -> dict[str, Any]:
    from dotshell.pipeline.mesh import mesh_stage

    # the mesh process reads cloud.ply, and no step from here on reads the cloud in this
    # process: let it go (133 MB through the mesh and normalize steps of the agar scan; issue 33)
    ctx.cloud = None
    return {"mesh": mesh_stage(ctx.store, ctx.profile, ctx.pm, ctx.bus,
                               ctx.options.get("node_distance_mm"), ctx._calib)}


def normalize_step(ctx: StepContext) -> dict[str, Any]:
    from dotshell.pipeline.normalize_outputs import normalize_stage

    o = ctx.options
    return {"normalize": normalize_stage(ctx.store, ctx.profile, ctx.pm, ctx.bus,
                                         o.get("normalizer"), o.get("min_sin_beta"),
                                         o.get("max_normal_spread_deg"), ctx._calib)}


def exports_step(ctx: StepContext) -> dict[str, Any]:
    out = {}
    for name, settings in ctx.profile.export.items():
        ctx.bus.emit(StepStarted(step=f"export {name}"))
        exporter = ctx.pm.create("exporter", name, settings, None, ctx.profile.source)
        paths = exporter.export(ctx.store.root)
        out[name] = [str(Path(p).relative_to(ctx.store.root)) for p in paths]
    return {"exports": out}


def forward_step(ctx: StepContext) -> dict[str, Any]:
    from dotshell.pipeline.mesh import forward_stage

    o = ctx.options
    return {"forward": forward_stage(ctx.store, o.get("source_mm"), o.get("mesh_dir", "."))}


def _has_transillumination(ctx: StepContext) -> bool:
    entry = ctx.store.manifest.get("transillumination") or {}
    return bool(entry.get("views"))


def _import_fit() -> None:
    import dotshell.pipeline.validate  # noqa: F401


STEPS: tuple[Step, ...] = (
    Step("calibration", (), calibration_step),
    Step("views", ("calibration",), views_step),
    Step("cloud", ("views",), cloud_step),
    Step("validation", ("cloud", "calibration"), validation_step,
         lambda ctx, base: ctx.profile.validation.shape == "cylinder", _import_fit),
    Step("previews", ("cloud", "views"), previews_step,
         lambda ctx, base: ctx.profile.outputs.previews),
    Step("mesh", ("cloud", "calibration"), mesh_step,
         lambda ctx, base: "mesh" in base or ctx.profile.mesh.after_scan),
    Step("normalize", ("mesh", "calibration"), normalize_step,
         lambda ctx, base: "normalize" in base or (
             _has_transillumination(ctx) and ctx.profile.mesh.after_scan
             and ctx.profile.normalize.after_scan)),
    Step("exports", ("cloud", "mesh"), exports_step,
         lambda ctx, base: bool(ctx.profile.export) and ctx.options.get("export", True)),
    Step("forward", ("mesh",), forward_step, lambda ctx, base: "forward" in base),
)
STEP_BY_NAME = {s.name: s for s in STEPS}


def import_ahead(names: Sequence[str], current: str) -> threading.Thread | None:
    """Start importing, in one background thread, what the steps of ``names`` after
    ``current`` need when ``current`` makes the last of their inputs (e.g. the validation's
    module while the cloud is merged). A failed import is left for the
    step itself to meet and report. Returns the thread, or None when there is nothing to do."""
    order = list(names)
    later = order[order.index(current) + 1:]
    work = [imports for n in later if (imports := STEP_BY_NAME[n].imports) is not None
            and current == max((r for r in STEP_BY_NAME[n].reads if r in order),
                               key=order.index, default=None)]
    if not work:
        return None

    def run() -> None:
        for fn in work:
            try:
                fn()
            except Exception:  # noqa: BLE001 - the step imports again and reports it
                pass

    thread = threading.Thread(target=run, name="dotshell-import-ahead", daemon=True)
    thread.start()
    return thread

