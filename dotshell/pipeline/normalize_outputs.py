"""Files of the normalization (docs/transillumination.md, "Outputs"), under ``normalize/``:

* ``view_VVV_src_SS.csv`` — one row per surface node: position (sample frame, mm), sin β, mask
  reason, pixels, radiance, intensity, the I0 of every normalizer, the truth when known;
* ``surface_normalized.vtu`` — the surface with those columns as point data, per view/source;
* ``view_VVV_src_SS_flat.tiff`` — the "flattened" image: the primary normalizer's I0 at every
  pixel that sees the sample, i.e. the image a planar sample facing the camera would give
  (float32, DN/ms; NaN off the sample);
* ``view_VVV_src_SS.png`` — preview: flat-fielded frame, node intensities and normalized I0;
* ``nirfast_vVVV_src_SS.paa`` — NIRFAST "standard" measurement data (source, det, active,
  amplitude, phase) at the ``[mesh.optodes]`` detectors, when the profile defines them.

:func:`normalize_stage` is the pipeline's normalize step: the normalization
(:mod:`dotshell.pipeline.normalize`) with these files written as it goes.
"""

from __future__ import annotations

import csv
import io
import time
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from dotshell.geometry.bvh import TriangleBVH
from dotshell.geometry.surface_map import MASK_REASONS, SurfaceView, resample_to_image
from dotshell.pipeline.normalize import Normalization, SourceResult, error_stats
from dotshell.profile.loader import Profile
from dotshell.run.layout import RunLayout
from dotshell.run.store import RunStore, atomic_write_bytes, atomic_write_text

if TYPE_CHECKING:
    from dotshell.geometry.calibration import RigCalibration
    from dotshell.events import EventBus
    from dotshell.plugins import PluginManager


def stem(r: SourceResult) -> str:
    return f"{RunLayout.view_stem(r.view)}_{r.source}"


def write_csv(store: RunStore, job: Normalization, r: SourceResult) -> str:
    buf = io.StringIO()
    w = csv.writer(buf)
    backends = list(r.normalized)
    w.writerow(["node", "x_mm", "y_mm", "z_mm", "sin_beta", "mask", "pixels", "radiance",
                "intensity", *[f"i0_{b}" for b in backends]]
               + (["i0_true"] if r.truth is not None else []))
    v = job.surface.vertices
    for k in range(len(v)):
        row = [k, *(f"{x:.4f}" for x in v[k]), f"{r.sin_beta[k]:.5f}",
               MASK_REASONS[r.light.mask[k]], f"{r.light.pixels[k]:.2f}",
               _g(r.light.radiance[k]), _g(r.light.intensity[k]),
               *(_g(r.normalized[b][k]) for b in backends)]
        if r.truth is not None:
            row.append(_g(r.truth[k]))
        w.writerow(row)
    name = RunLayout.normalize_file(f"{stem(r)}.csv")
    atomic_write_text(store.path(name), buf.getvalue())
    return name


def _g(x: float) -> str:
    return "" if not np.isfinite(x) else f"{x:.6g}"


def write_vtu(store: RunStore, job: Normalization, results: list[SourceResult]) -> str:
    import meshio

    from dotshell.fem.meshfiles import _atomic_meshio

    data: dict[str, np.ndarray] = {}
    for r in results:
        data[f"sin_beta_v{r.view:03d}"] = r.sin_beta
        key = f"v{r.view:03d}_{r.source}"
        data[f"mask_{key}"] = r.light.mask.astype(np.int32)
        data[f"intensity_{key}"] = r.light.intensity
        for b, est in r.normalized.items():
            data[f"i0_{b}_{key}"] = est
        if r.truth is not None:
            data[f"i0_true_{key}"] = r.truth
    mesh = meshio.Mesh(job.surface.vertices, [("triangle", job.surface.triangles)],
                       point_data=data)
    name = RunLayout.normalize_file("surface_normalized.vtu")
    _atomic_meshio(store.path(name), mesh, "vtu")
    return name


def write_flat_image(store: RunStore, r: SourceResult, image: np.ndarray) -> str:
    ok, buf = cv2.imencode(".tiff", image.astype(np.float32))
    if not ok:
        raise OSError("could not encode the flattened image as TIFF")
    name = RunLayout.normalize_file(f"{stem(r)}_flat.tiff")
    atomic_write_bytes(store.path(name), buf.tobytes())
    return name


def write_preview(store: RunStore, r: SourceResult, frame: np.ndarray, raw_img: np.ndarray,
                  flat_img: np.ndarray, primary: str) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    finite = np.concatenate([raw_img[np.isfinite(raw_img)], flat_img[np.isfinite(flat_img)]])
    vmax = float(np.percentile(finite, 99.5)) if finite.size else 1.0
    ys, xs = np.nonzero(np.isfinite(flat_img))
    crop = (slice(max(ys.min() - 10, 0), ys.max() + 11), slice(max(xs.min() - 10, 0), xs.max() + 11)) \
        if len(ys) else (slice(None), slice(None))
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.6))
    panels = ((frame, "flat-fielded frame [DN/ms]"),
              (raw_img, "node intensity I (raw, none)"),
              (flat_img, f"normalized I0 ({primary})"))
    for ax, (img, title) in zip(axes, panels):
        im = ax.imshow(img[crop], cmap="magma", vmin=0, vmax=vmax)
        ax.set_title(title, fontsize=9)
        ax.set_axis_off()
    fig.colorbar(im, ax=list(axes), shrink=0.8, label="DN/ms")
    fig.suptitle(f"view {r.view} ({r.angle_deg:g}°), {r.source}: {r.stats['used']} of "
                 f"{r.stats['nodes']} nodes used", fontsize=10)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    name = RunLayout.normalize_file(f"{stem(r)}.png")
    atomic_write_bytes(store.path(name), buf.getvalue())
    return name


def write_paa(store: RunStore, r: SourceResult, amplitudes: np.ndarray) -> str:
    """NIRFAST standard data: header ``source det active amplitude phase``, one row per
    detector (1-based indices; this image is source 1; inactive where no value; phase 0 for
    continuous-wave light)."""
    lines = ["\t".join(f"{h:<10}" for h in ("source", "det", "active", "amplitude", "phase"))]
    for d, a in enumerate(amplitudes, 1):
        active = int(np.isfinite(a))
        lines.append("\t".join(f"{x:<10g}" for x in (1, d, active, a if active else 0.0, 0.0)))
    name = RunLayout.normalize_file(f"nirfast_v{r.view:03d}_{r.source}.paa")
    atomic_write_text(store.path(name), "\n".join(lines) + "\n")
    return name


def pooled(results: list[SourceResult]) -> dict[str, Any]:
    """Error statistics over all views and sources together, per normalizer."""
    if not results or results[0].truth is None:
        return {}
    truth = np.concatenate([r.truth for r in results])
    return {b: error_stats(np.concatenate([r.normalized[b] for r in results]), truth)
            for b in results[0].normalized}


class OutputWriter:
    """Writes each view's files as the normalization produces them, then the summary."""

    def __init__(self, store: RunStore, profile: Profile, job: Normalization) -> None:
        self.store, self.profile, self.job = store, profile, job
        detectors = np.asarray(profile.mesh.optodes.detectors_mm,
                               float).reshape(-1, 3)
        # the surface point nearest to each detector (sample frame), found once for all images
        self.at_detectors = TriangleBVH(job.surface.vertices, job.surface.triangles).closest(
            detectors) if len(detectors) else None
        self.entries: list[dict[str, Any]] = []
        store.path(RunLayout.NORMALIZE).mkdir(exist_ok=True)

    def view(self, geometry: SurfaceView, pairs: list[tuple[SourceResult, np.ndarray]]) -> None:
        job, store = self.job, self.store
        for r, frame in pairs:
            primary = r.normalized[job.primary]
            flat_img = resample_to_image(geometry, primary)
            files = {"csv": write_csv(store, job, r),
                     "flattened": write_flat_image(store, r, flat_img)}
            if self.profile.outputs.previews:
                raw_img = resample_to_image(geometry, r.light.intensity)
                files["preview"] = write_preview(store, r, frame, raw_img, flat_img, job.primary)
            if self.at_detectors is not None:
                files["nirfast"] = write_paa(store, r, self.at_detectors.interpolate(primary))
            self.entries.append({"view": r.view, "angle_deg": r.angle_deg, "source": r.source,
                                 "target_mm": r.target_mm, **r.stats, "files": files})

    def summary(self, results: list[SourceResult]) -> dict[str, Any]:
        job = self.job
        section = {"normalizer": job.primary,
                   "compare": [b for b in job.models if b != job.primary],
                   "min_sin_beta": job.cfg.min_sin_beta,
                   "max_normal_spread_deg": job.cfg.max_normal_spread_deg,
                   "flat_field": job.flat is not None,
                   "mask_reasons": list(MASK_REASONS), "sources": self.entries,
                   "masked_total": _sum_masks(self.entries),
                   "vtu": write_vtu(self.store, job, results)}
        truth = pooled(results)
        if truth:
            section["vs_truth"] = truth
        return section


def _sum_masks(entries: list[dict[str, Any]]) -> dict[str, int]:
    total = {r: 0 for r in MASK_REASONS}
    for e in entries:
        for r, n in e["masked"].items():
            total[r] += n
    return total


def normalize_stage(store: RunStore, profile: Profile, pm: PluginManager, bus: EventBus,
                    normalizer: str | None = None, min_sin_beta: float | None = None,
                    max_normal_spread_deg: float | None = None,
                    calib: RigCalibration | None = None) -> dict[str, Any]:
    """Normalize a run and write its outputs; returns the report section. ``calib``: the run's
    calibration when the caller has it loaded (else read from the run)."""
    t0 = time.perf_counter()
    job = Normalization(store, profile, pm, bus, normalizer, min_sin_beta, max_normal_spread_deg,
                        calib)
    writer = OutputWriter(store, profile, job)
    results = job.run(writer.view)
    section = writer.summary(results)
    section["seconds"] = round(time.perf_counter() - t0, 3)
    store.write_json(RunLayout.normalize_file(RunLayout.REPORT), section)
    return section
