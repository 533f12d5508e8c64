"""Intensity normalization of trans-illumination frames on the scanned surface
(``dotshell normalize RUN`` and the end of a scan that captured them).

For every view and source position: dark-subtract and flat-field the frame (DN per ms of
exposure, relative to the principal point), map it onto the run's ``surface.ply`` nodes
(:mod:`dotshell.geometry.surface_map`: occlusion by ray casting, sin β per node, masks), and
divide the node intensities by the orientation factor of the profile's ``[normalizer]`` backend
(default ``diffuse-fresnel``) and of each ``[normalize] compare`` backend. When the run recorded
the true light (a simulated rig writes it to ``truth.json``, :mod:`dotshell.run.truth`), every
backend is scored against it. Outputs are written by
:mod:`dotshell.pipeline.normalize_outputs` (whose ``normalize_stage`` runs the whole step); the figures go to ``normalize/report.json`` and the
``normalize`` section of ``report.json``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np

from dotshell.devices import SurfaceRadiance
from dotshell.errors import CalibrationError, DotshellError, RunError
from dotshell.events import EventBus, StepProgress, StepStarted
from dotshell.fem.meshes import TriangleSurface
from dotshell.run.framecheck import FrameSpec
from dotshell.geometry.calibration import RigCalibration
from dotshell.geometry.bvh import TriangleBVH
from dotshell.geometry.raycast import ClosestPoints
from dotshell.geometry.surface_map import (OK, NodeLight, SurfaceView, mask_counts,
                                           node_intensities, normal_spread_deg, view_surface)
from dotshell.normalizer import Normalizer
from dotshell.plugins import PluginManager
from dotshell.pipeline.transillum import source_names
from dotshell.profile.loader import Profile
from dotshell.settings import validate_settings
from dotshell.profile.transillum import NORMALIZE_SCHEMA
from dotshell.run.layout import RunLayout
from dotshell.run.store import RunStore
from dotshell.run.truth import TRUTH_FILE, read_transillumination_truth

DEFAULT_NORMALIZER = "diffuse-fresnel"
ViewCallback = Callable[[SurfaceView, list[tuple["SourceResult", np.ndarray]]], None]
FLAT_SIGMA_PX = 2.0      # smoothing of the flat field (its shot noise must not enter the data)
FLAT_MIN = 0.05          # flat-field values below this share of the centre are unusable


@dataclass
class SourceResult:
    """Normalization of one (view, source) image."""

    view: int
    angle_deg: float
    source: str
    target_mm: list[float] | None
    light: NodeLight
    sin_beta: np.ndarray                 # (N,) per node, this view
    normalized: dict[str, np.ndarray]    # backend name → I0 estimate per node (NaN masked)
    truth: np.ndarray | None             # true I0 per node, if the run recorded it
    stats: dict[str, Any]


def normalizers(profile: Profile, pm: PluginManager, override: str | None) -> dict[str, Normalizer]:
    """The primary normalizer first, then the ``compare`` ones (each once)."""
    section = profile.role("normalizer")
    primary = override or (section["backend"] if section else DEFAULT_NORMALIZER)
    names = [primary] + [n for n in profile.normalize.compare if n != primary]
    out = {}
    for name in dict.fromkeys(names):
        settings = dict(section["settings"]) if section and section["backend"] == name else {}
        info = pm.backend("normalizer", name, profile.source)
        settings = validate_settings(info.backend.settings_schema, settings, profile.source,
                                     "normalizer.settings")
        if settings.get("refractive_index") == 0.0:  # documented: 0 = the sample's [mesh.optics]
            settings["refractive_index"] = profile.mesh.optics.refractive_index
        out[name] = pm.create("normalizer", name, settings, None, profile.source)
    return out


def _required(store: RunStore, name: str, error: type[DotshellError], why: str) -> Path:
    """The run's file ``name``, or ``error`` saying ``why`` it is needed and how to make it."""
    path = store.path(name)
    if not path.is_file():
        raise error(f"{store.root} has no {name}: {why}")
    return path


def _load_surface(store: RunStore) -> TriangleSurface:
    from dotshell.fem.meshfiles import read_surface

    return read_surface(_required(
        store, RunLayout.SURFACE, RunError, "normalization maps the images onto the scanned "
        f"surface. Run `dotshell mesh {store.root}` first, or scan with [mesh] after_scan = true."))


#: Cloud points searched at a time by :func:`unscanned_nodes` (a float64 copy and a k-d tree
#: of ~50 MB), where the whole 8.3 M-point agar cloud as float64 and its tree took ~0.3 GB:
#: the scan's peak after the capture (issue 33).
CLOUD_CHUNK = 1 << 20


def unscanned_nodes(store: RunStore, surface: TriangleSurface, max_distance_mm: float,
                    chunk: int = CLOUD_CHUNK) -> np.ndarray:
    """Nodes farther than ``max_distance_mm`` from every point of the run's cloud: surface the
    mesher made up (the closed bottom, filled holes), whose orientation is a guess. The cloud
    is read and searched ``chunk`` points at a time (a node is scanned when any chunk has a
    point within the distance: the same nodes as one search of the whole cloud)."""
    from scipy.spatial import cKDTree

    from dotshell.run.ply import point_chunks

    unscanned = np.ones(len(surface.vertices), bool)
    for part in point_chunks(_required(
            store, RunLayout.CLOUD, RunError, "the surface's nodes cannot be checked against "
            f"the scanned points. Re-run `dotshell reconstruct {store.root}`."), chunk):
        todo = np.flatnonzero(unscanned)
        if todo.size:
            dist, _ = cKDTree(part).query(surface.vertices[todo],
                                          distance_upper_bound=max_distance_mm)
            unscanned[todo[np.isfinite(dist)]] = False
    return unscanned


def _load_calibration(store: RunStore) -> RigCalibration:
    return RigCalibration.load(_required(
        store, RunLayout.CALIBRATION, CalibrationError, "its views cannot be mapped onto the "
        f"surface. Give one with `dotshell reconstruct {store.root} --calibration FILE`."))


def flat_field(store: RunStore, entry: dict[str, Any], calib: RigCalibration,
               bus: EventBus) -> np.ndarray | None:
    """Relative flat field (1 at the principal point), or None without one."""
    if not entry.get("flat_field"):
        bus.warn(f"{store.root}: no flat field; camera vignetting stays in the intensities.")
        return None
    flat = _float(store.read_image(store.path(entry["flat_field"]), "cannot flat-field"))
    half_path = store.trans_path("flat_half")
    if half_path.is_file():  # full − half exposure: no black level, no stray light
        flat = flat - _float(store.read_image(half_path, "cannot flat-field"))
    _check_size(flat, calib, store.path(entry["flat_field"]))
    flat = cv2.GaussianBlur(flat, (0, 0), FLAT_SIGMA_PX)
    cx, cy = (int(round(c)) for c in calib.camera.K[[0, 1], [2, 2]])
    centre = float(np.median(flat[max(cy - 7, 0):cy + 8, max(cx - 7, 0):cx + 8]))
    if not centre > 0:
        raise RunError(f"{store.path(entry['flat_field'])}: the flat field is dark at the "
                       "principal point; capture it again with the uniform field in front of the "
                       "lens.")
    rel = flat / centre
    rel[rel < FLAT_MIN] = np.nan
    return rel


def _float(img: np.ndarray) -> np.ndarray:
    return img.astype(np.float32)


def _check_size(img: np.ndarray, calib: RigCalibration, path: Path) -> None:
    if (img.shape[1], img.shape[0]) != calib.camera.size:
        raise RunError(f"{path} is {img.shape[1]}x{img.shape[0]} px but the calibration's camera "
                       f"is {calib.camera.size[0]}x{calib.camera.size[1]}; the image does not "
                       "belong to this calibration.")


def transillumination_entry(store: RunStore) -> dict[str, Any]:
    """The manifest's ``transillumination`` section, or a :class:`RunError` if the run has no
    trans-illumination frames."""
    entry = store.manifest.get("transillumination")
    if not entry or not entry.get("views"):
        raise RunError(f"{store.run_root} has no trans-illumination frames: there is nothing "
                       "to normalize. Scan with [transillumination] enabled = true (and a "
                       "[light_source]), see docs/transillumination.md.")
    return entry


def _checked(img: np.ndarray, calib: RigCalibration, bit_depth: int, path: Path) -> np.ndarray:
    """A stored trans-illumination image if it is a frame of this run's camera (size of the
    calibration's camera, dtype and range of ``bit_depth``)."""
    spec = FrameSpec(*calib.camera.size, bit_depth)
    return spec.check(img, str(path), "The image does not belong to this run; restore the "
                      "run's frames from a backup, or capture the trans-illumination again.")


class TruthAtNodes:
    """The true I0 a run recorded (:mod:`dotshell.run.truth`), read at the nodes of the scanned
    surface: each node takes the value at its closest point of the true surface, NaN farther
    than the field's ``max_snap_mm``."""

    def __init__(self, store: RunStore, nodes_mm: np.ndarray, bus: EventBus) -> None:
        self.nodes_mm = nodes_mm
        self.recorded = read_transillumination_truth(store.run_root)
        self._closest: tuple[SurfaceRadiance, ClosestPoints] | None = None
        if self.recorded is None:
            bus.info(f"{store.run_root} has no {TRUTH_FILE} with the true trans-illumination "
                     "light (only a simulated rig records it): the normalization is not scored "
                     "against the truth.")

    def at(self, view: int, source: str) -> np.ndarray | None:
        """True I0 per node for ``source`` at ``view``; None if the run recorded none."""
        field = self.recorded.field(view, source) if self.recorded is not None else None
        if field is None:
            return None
        at = self._closest_points(field)
        return np.where(at.distance_mm <= field.max_snap_mm, at.interpolate(field.radiance),
                        np.nan)

    def _closest_points(self, field: SurfaceRadiance) -> ClosestPoints:
        """The nodes' closest points on the field's surface (found once per surface)."""
        last = self._closest
        if last is None or not (np.array_equal(last[0].vertices_mm, field.vertices_mm)
                                and np.array_equal(last[0].triangles, field.triangles)):
            scene = TriangleBVH(field.vertices_mm, field.triangles)
            last = self._closest = (field, scene.closest(self.nodes_mm))
        return last[1]


def error_stats(estimate: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """Relative error of ``estimate`` against ``truth`` over nodes where both are finite:
    median and 95th percentile of |error|, signed median (all in %)."""
    ok = np.isfinite(estimate) & np.isfinite(truth) & (truth > 0)
    if not ok.any():
        return {"nodes": 0}
    rel = estimate[ok] / truth[ok] - 1.0
    return {"nodes": int(ok.sum()),
            "median_abs_pct": round(float(np.median(np.abs(rel))) * 100, 3),
            "p95_abs_pct": round(float(np.percentile(np.abs(rel), 95)) * 100, 3),
            "median_signed_pct": round(float(np.median(rel)) * 100, 3)}


def checked_overrides(min_sin_beta: float | None, max_normal_spread_deg: float | None
                      ) -> dict[str, float]:
    """The command line's ``--min-sin-beta`` and ``--max-normal-spread`` (None: not given),
    checked against the bounds of their ``[normalize]`` keys (ProfileError naming the flag)."""
    out: dict[str, float] = {}
    for flag, key, value in (("--min-sin-beta", "min_sin_beta", min_sin_beta),
                             ("--max-normal-spread", "max_normal_spread_deg",
                              max_normal_spread_deg)):
        if value is not None:
            out.update(validate_settings({key: NORMALIZE_SCHEMA[key]}, {key: value}, flag,
                                         "normalize"))
    return out


class Normalization:
    """Normalizes one run's trans-illumination frames (see the module docstring)."""

    def __init__(self, store: RunStore, profile: Profile, pm: PluginManager, bus: EventBus,
                 normalizer: str | None = None, min_sin_beta: float | None = None,
                 max_normal_spread_deg: float | None = None,
                 calib: RigCalibration | None = None) -> None:
        self.store, self.profile, self.bus = store, profile, bus
        overrides: dict[str, Any] = checked_overrides(min_sin_beta, max_normal_spread_deg)
        self.cfg = replace(profile.normalize, **overrides)
        self.entry = transillumination_entry(store)
        self.surface = _load_surface(store)
        self.unscanned = unscanned_nodes(store, self.surface, self.cfg.max_cloud_distance_mm)
        self.crease = normal_spread_deg(self.surface) > self.cfg.max_normal_spread_deg
        self.calib = calib or _load_calibration(store)
        self.models = normalizers(profile, pm, normalizer)
        self.primary = next(iter(self.models))
        self.flat = flat_field(store, self.entry, self.calib, bus)
        self.truth = TruthAtNodes(store, self.surface.vertices, bus)
        self.bit_depth = int(self.entry.get("camera_bit_depth", 16))
        self.full_scale = (1 << self.bit_depth) - 1
        self.angles = {v["index"]: v["angle_deg"] for v in store.manifest["views"]}
        targets = self.entry["targets_mm"]  # [None] for a source that was not aimed
        self.targets = dict(zip(source_names(len(targets)), targets))

    def run(self, each_view: ViewCallback | None = None) -> list[SourceResult]:
        """Normalize every stored view; ``each_view(geometry, [(result, image), ...])`` is called
        per view (to write its files) before the next view's images are read."""
        views = sorted(int(v) for v in self.entry["views"])
        self.bus.emit(StepStarted(step="normalize", total=len(views)))
        results = []
        for done, view in enumerate(views, 1):
            if view not in self.angles:
                raise RunError(f"{self.store.root}: trans-illumination view {view} is not a view "
                               "of this run's manifest; the run is damaged.")
            geometry = view_surface(self.surface, self.calib, self.angles[view],
                                    self.cfg.min_sin_beta, self.unscanned, self.crease)
            pairs = [self._source(geometry, view, name)
                     for name in self.entry["views"][str(view)] if name != "dark"]
            if each_view is not None:
                each_view(geometry, pairs)
            results += [r for r, _ in pairs]
            self.bus.emit(StepProgress(step="normalize", done=done, total=len(views)))
        return results

    def _image(self, view: int, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(DN per ms, flat-fielded; saturated-pixel mask) of one stored frame."""
        path = self.store.trans_path(name, view)
        raw = _checked(self.store.read_image(path, f"view {view} cannot be normalized"),
                       self.calib, self.bit_depth, path)
        saturated = raw >= self.cfg.saturation_fraction * self.full_scale
        img = _float(raw)
        if "dark" in self.entry["views"][str(view)]:
            dark = self.store.trans_path("dark", view)
            img = img - _float(_checked(self.store.read_image(
                dark, f"view {view} cannot be dark-subtracted"), self.calib, self.bit_depth, dark))
        img = img / float(self.entry["exposure_ms"])
        if self.flat is not None:
            img = img / self.flat
            saturated |= ~np.isfinite(self.flat)
        return img, saturated

    def _source(self, geometry: SurfaceView, view: int,
                name: str) -> tuple[SourceResult, np.ndarray]:
        img, saturated = self._image(view, name)
        light = node_intensities(geometry, img, saturated, self.cfg.min_pixels)
        self._warn_saturation(view, name, saturated, geometry)
        estimates = {}
        good = light.mask == OK
        for backend, model in self.models.items():
            factor = model.orientation_factor(np.clip(geometry.sin_beta, 1e-6, 1.0))
            estimates[backend] = np.where(good, light.intensity / factor, np.nan)
        target = self.targets.get(name)
        truth = self.truth.at(view, name)
        if truth is not None:
            truth = np.where(good, truth, np.nan)
        stats = self._stats(light, geometry, estimates, truth)
        return SourceResult(view, geometry.angle_deg, name, target, light, geometry.sin_beta,
                            estimates, truth, stats), img

    def _warn_saturation(self, view: int, name: str, saturated: np.ndarray,
                         geometry: SurfaceView) -> None:
        n = int(saturated.ravel()[geometry.pixel_index].sum())
        if n:
            self.bus.warn(f"{self.store.trans_path(name, view)}: {n} saturated pixels on the "
                          "sample; their nodes are masked as 'saturated'. Lower "
                          "[transillumination] exposure_ms or the source power.")

    def _stats(self, light: NodeLight, geometry: SurfaceView, estimates: dict[str, np.ndarray],
               truth: np.ndarray | None) -> dict[str, Any]:
        good = light.mask == OK
        stats: dict[str, Any] = {
            "nodes": int(len(light.mask)), "used": int(good.sum()),
            "masked": mask_counts(light.mask),
            "sin_beta_used": {"min": _r(np.min(geometry.sin_beta[good])) if good.any() else None,
                              "median": _r(np.median(geometry.sin_beta[good])) if good.any() else None},
        }
        if truth is not None:
            stats["vs_truth"] = {b: error_stats(e, truth) for b, e in estimates.items()}
        return stats


def _r(x: float) -> float:
    return round(float(x), 4)
