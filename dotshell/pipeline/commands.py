"""Re-processing commands on an existing run — ``reconstruct``, ``mesh``, ``normalize``,
``forward`` — as the same engine asked for different targets. Each validates its inputs first,
then writes a new generation and publishes it only when every step succeeded; a failure leaves
the run's published products exactly as they were (and says so in the manifest's reason)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable

from dotshell.errors import CalibrationError, RunError
from dotshell.events import EventBus
from dotshell.geometry.calibration import RigCalibration
from dotshell.geometry.opencv_io import load_any_calibration
from dotshell.pipeline.engine import RunJob, process
from dotshell.pipeline.steps import require_turntable_axis
from dotshell.plugins import PluginManager
from dotshell.run.layout import RunLayout
from dotshell.run.store import RunStore

if TYPE_CHECKING:
    from dotshell.pipeline.scan import ScanResult


def reprocess(run_dir: Path | str, pm: PluginManager, command: str, targets: Iterable[str],
              bus: EventBus | None = None, options: dict[str, Any] | None = None,
              targets_if_calibration: Iterable[str] | None = None) -> dict[str, Any]:
    """Run ``targets`` on a run as job ``command``; returns the published report."""
    from dotshell.pipeline.scan import load_run_profile

    bus = bus or EventBus()
    options = dict(options or {})
    store = RunStore.open(Path(run_dir))
    unsub = bus.subscribe(lambda ev: store.append_event(ev.to_dict()))
    try:
        profile = load_run_profile(store, pm)
        if options.get("calibration_file"):
            options["calibration"] = check_calibration_for_run(options["calibration_file"],
                                                               store)
            targets = targets_if_calibration or targets
        with RunJob(store, command, bus) as job:
            return process(job, profile, pm, targets, options)
    finally:
        unsub()
        store.close()


def reconstruct_run(run_dir: Path | str, pm: PluginManager, bus: EventBus | None = None,
                    calibration_file: str | None = None) -> ScanResult:
    """Re-process a run from its frames on disk into a new generation (views not fully
    captured are skipped with a warning); with ``calibration_file``, that calibration is
    validated first and used for the new generation. Nothing of earlier generations changes."""
    from dotshell.pipeline.scan import ScanResult

    report = reprocess(run_dir, pm, "reconstruct", ("views",), bus,
                       {"calibration_file": calibration_file} if calibration_file else {},
                       targets_if_calibration=("calibration",))
    return ScanResult(Path(run_dir), report.get("status", "completed"), report)


def check_calibration_for_run(path: str | Path, store: RunStore) -> RigCalibration:
    """A calibration file that can re-process this run: valid, and its camera the size of the
    run's frames. Checked before anything is written."""
    calib = load_any_calibration(path)
    captured = RigCalibration.load(store.path(RunLayout.CALIBRATION))
    if calib.camera.size != captured.camera.size:
        raise CalibrationError(
            f"{path}: its camera is {calib.camera.size[0]}x{calib.camera.size[1]} px but the run's "
            f"frames are {captured.camera.size[0]}x{captured.camera.size[1]} px; give the "
            "calibration of the camera at the resolution the run was captured with.")
    require_turntable_axis(calib, [v["angle_deg"] for v in store.manifest["views"]], str(path))
    if calib.projector.size != captured.projector.size:
        raise CalibrationError(
            f"{path}: its projector is {calib.projector.size[0]}x{calib.projector.size[1]} px "
            f"but the run's patterns were made for {captured.projector.size[0]}x"
            f"{captured.projector.size[1]} px; give the calibration of this projector.")
    return calib


@dataclass
class MeshRunResult:
    run_dir: Path
    report: dict[str, Any]


def mesh_run(run_dir: Path | str, pm: PluginManager, bus: EventBus | None = None,
             node_distance_mm: float | None = None, export: bool = True) -> MeshRunResult:
    """``dotshell mesh RUN``: mesh the run's cloud (and run the profile's exporters unless
    ``export`` is False) into a new generation."""
    options: dict[str, Any] = {"export": export}
    if node_distance_mm is not None:
        options["node_distance_mm"] = node_distance_mm
    targets = ["mesh", "exports"] if export else ["mesh"]
    return MeshRunResult(Path(run_dir), reprocess(run_dir, pm, "mesh", targets, bus, options))


def normalize_run(run_dir: Path | str, pm: PluginManager, bus: EventBus | None = None,
                  normalizer: str | None = None, min_sin_beta: float | None = None,
                  max_normal_spread_deg: float | None = None) -> dict[str, Any]:
    """``dotshell normalize RUN``: normalize the trans-illumination frames on the run's surface
    into a new generation; returns the ``normalize`` report section."""
    from dotshell.pipeline.normalize import checked_overrides, transillumination_entry

    checked_overrides(min_sin_beta, max_normal_spread_deg)  # before anything is read or made
    transillumination_entry(RunStore.open(Path(run_dir)))
    options = {"normalizer": normalizer, "min_sin_beta": min_sin_beta,
               "max_normal_spread_deg": max_normal_spread_deg}
    return reprocess(run_dir, pm, "normalize", ["normalize"], bus, options)["normalize"]


def forward_run(run_dir: Path | str, pm: PluginManager | None = None,
                source_mm: list[float] | None = None, mesh_dir: str = ".",
                bus: EventBus | None = None) -> dict[str, Any]:
    """``dotshell forward RUN``: CW fluence for a point source on the run's volume mesh
    (``forward.vtu`` beside it) in a new generation; returns the ``forward`` section."""
    if pm is None:
        from dotshell.plugins import get_plugin_manager

        pm = get_plugin_manager()
    if Path(mesh_dir).is_absolute() or ".." in Path(mesh_dir).parts:
        raise RunError(f"--mesh-dir {mesh_dir!r} leads outside the run's products; give a mesh "
                       "directory inside the run, e.g. '.' or 'meshes/2mm'.")
    options = {"source_mm": source_mm, "mesh_dir": mesh_dir}
    return reprocess(run_dir, pm, "forward", ["forward"], bus, options)["forward"]
