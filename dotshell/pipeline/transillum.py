"""Trans-illumination capture: at each view of a scan, with the stage where the fringe frames
were taken and the projector dark, capture one frame per source position with the light source
on, and (``dark = true``) one with it off; once per scan a uniform field at the trans exposure and at half of it (the flat field).

Frames go through the scan's :class:`~dotshell.pipeline.acquire.FrameWriter` into
``transillumination/`` (docs/run-directory.md) and are listed in the manifest's
``transillumination`` section. A :class:`~dotshell.errors.DeviceError` is retried like a fringe
frame; a source that cannot be aimed at the profile's targets is a profile error before anything
is captured.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any, cast

import numpy as np

from dotshell.devices import (ExposureControl, FlatFieldReference, SurfaceRadiance, Targetable,
                              TransilluminationTruth, implements)
from dotshell.errors import ProfileError
from dotshell.events import EventBus, StepStarted
from dotshell.run.framecheck import FrameSpec
from dotshell.pipeline.acquire import FrameWriter, check_frame, with_retries
from dotshell.rig.assembly import Rig
from dotshell.profile.sections import ScanSettings, TransilluminationSettings
from dotshell.run.layout import RunLayout
from dotshell.run.store import RunStore
from dotshell.run.truth import record_transillumination_truth


def source_names(n_targets: int) -> list[str]:
    """Frame names of the source positions of one view (``src_00`` ...)."""
    return [f"src_{j:02d}" for j in range(max(1, n_targets))]


class TransilluminationCapture:
    """Captures the trans-illumination frames of one scan."""

    def __init__(self, rig: Rig, store: RunStore, settings: TransilluminationSettings,
                 scan: ScanSettings,
                 writer: FrameWriter, bus: EventBus, base_dir: Path) -> None:
        self.rig, self.store, self.s, self.scan = rig, store, settings, scan
        self.writer, self.bus = writer, bus
        light = rig.light_source
        where = rig.profile.source
        if light is None:
            raise ProfileError(f"{where}: [transillumination] enabled = true needs a "
                               "[light_source].")
        self.light = light
        self.targets = [tuple(t) for t in settings.targets_mm]
        if self.targets and not isinstance(self.light, Targetable):
            raise ProfileError(
                f"{where}: [transillumination] targets_mm lists {len(self.targets)} source "
                f"position(s) but the light source ({rig.profile.required_role('light_source')['backend']}) "
                "cannot be aimed; remove targets_mm or use a targetable source (galvo).")
        self.flat_device = next((d for d in rig.devices.values()
                                 if isinstance(d, FlatFieldReference)), None)
        self.flat_file = self._flat_file(settings.flat_field, base_dir, where)
        self.names = source_names(len(self.targets))
        self.spec = FrameSpec.of_camera(rig.camera)
        #: a simulated source knows the true light: recorded in the run (truth.json) per view
        self.knows_truth = implements(self.light, TransilluminationTruth)

    @staticmethod
    def _flat_file(value: str, base_dir: Path, where: str) -> Path | None:
        if value in ("capture", "none"):
            return None
        path = (base_dir / value).resolve()
        if not path.is_file():
            raise ProfileError(f"{where}: [transillumination] flat_field = {value!r}: {path} does "
                               "not exist. Give an image of a uniform field taken with this "
                               "camera, or 'capture' / 'none'.")
        return path

    def manifest_entry(self) -> dict[str, Any]:
        return {"exposure_ms": self.s.exposure_ms,
                "camera_bit_depth": int(self.rig.camera.bit_depth),
                "targets_mm": [list(t) for t in self.targets] or [None],
                "frame_names": self.expected_names(),
                "flat_field": None, "views": {}}

    def _capture(self, what: str) -> np.ndarray:
        return check_frame(self.rig, self.spec, with_retries(
            self.rig.camera.capture, self.scan.retries, what, self.bus), what)

    def _dark_projector(self) -> None:
        w, h = self.rig.projector.resolution
        self.rig.projector.show(np.zeros((h, w), np.uint8))

    def _exposure(self, ms: float) -> None:
        if isinstance(self.rig.camera, ExposureControl):
            self.rig.camera.set_exposure(ms)

    def capture_flat_field(self) -> str | None:
        """The flat-field reference into the run; returns its path in the run, or None (with a
        warning) when there is none."""
        entry = self.store.manifest["transillumination"]
        if self.flat_file is not None:
            target = self.store.trans_path("flat")
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(self.flat_file, target)
        elif self.s.flat_field == "capture" and self.flat_device is not None:
            self._capture_flat_pair(self.flat_device)
        else:
            why = ("flat_field = 'none'" if self.s.flat_field == "none" else
                   "no device of this rig can show the camera a uniform field")
            self.bus.warn(f"trans-illumination without a flat field ({why}): camera vignetting "
                          "stays in the normalized intensities. Set [transillumination] "
                          "flat_field to an image of a uniform field.")
            return None
        entry["flat_field"] = RunLayout.trans_frame("flat")
        self.store.update_manifest(transillumination=entry)
        return entry["flat_field"]

    def _capture_flat_pair(self, device: FlatFieldReference) -> None:
        """The uniform field at the trans exposure and at half of it. Their difference is the
        flat field without the black level or any light that does not scale with exposure (a
        dark frame with the diffuser taken away would also subtract the scene's ambient light,
        which the diffuser hides). A camera without exposure control gives one frame."""
        self.bus.emit(StepStarted(step="flat field"))
        self._dark_projector()
        exposures = [("flat", self.s.exposure_ms)]
        if isinstance(self.rig.camera, ExposureControl):
            exposures.append(("flat_half", self.s.exposure_ms / 2))
        else:
            self.bus.warn("the camera has no exposure control: the flat field keeps the black "
                          "level (one frame, no half-exposure frame to subtract).")
        try:
            device.flat_field(True)
            for name, ms in exposures:
                self._exposure(ms)
                frame = self._capture(f"flat-field frame {name!r}")
                self.writer.put_path(self.store.trans_path(name), frame,
                                     f"flat-field frame {name!r}")
        finally:
            device.flat_field(False)
            self._exposure(self.scan.exposure_ms)
        self.writer.queue.join()
        self.writer.check()

    def expected_names(self) -> list[str]:
        """The frame names a fully trans-illuminated view has."""
        return self.names + (["dark"] if self.s.dark else [])

    def covers(self, view: int) -> bool:
        """Whether this view is trans-illuminated ([transillumination] views; empty = all)."""
        return not self.s.views or view in self.s.views

    def run_view(self, view: int) -> list[str]:
        """Capture this view's trans-illumination frames (stage already in place); returns the
        names written. The light source is off again afterwards, whatever happens."""
        self._exposure(self.s.exposure_ms)
        self._dark_projector()
        written: list[str] = []
        truth: dict[str, SurfaceRadiance] = {}
        try:
            try:
                self.light.set(True)
                targets: list[tuple[Any, ...] | None] = [*self.targets] or [None]
                for name, target in zip(self.names, targets):
                    if target is not None and isinstance(self.light, Targetable):
                        self.light.aim(target)
                    self._take(view, name)
                    written.append(name)
                    if self.knows_truth:  # None: where the un-aimed source points now
                        truth[name] = cast(TransilluminationTruth,
                                           self.light).true_surface_radiance(
                            self.store.manifest["views"][view]["angle_deg"], target)
            finally:
                self.light.set(False)
            if self.s.dark:
                self._take(view, "dark")
                written.append("dark")
        finally:
            self.writer.queue.join()  # every frame taken is on disk and listed; a frame
            entry = self.store.manifest["transillumination"]  # not written is not listed
            entry["views"][str(view)] = [n for n in written
                                         if self.store.trans_path(n, view).is_file()]
            self.store.update_manifest(transillumination=entry)
        self.writer.check()
        record_transillumination_truth(self.store, view,
                                       self.rig.profile.required_role("light_source")["backend"], truth)
        self._exposure(self.scan.exposure_ms)
        return written

    def _take(self, view: int, name: str) -> None:
        frame = self._capture(f"view {view}, trans-illumination {name}")
        self.writer.put_path(self.store.trans_path(name, view), frame,
                             f"trans-illumination frame {name!r} of view {view}")
