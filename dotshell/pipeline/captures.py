"""Reconstruction of capture sequences made elsewhere (another rig, another program).

A *layout file* (TOML, see ``docs/layouts.md`` and ``layouts/*.toml``; read by
:mod:`dotshell.run.capture_layouts`) says how the sequence was made: the file names, the frame order
(white, black, column bits, row bits), bit order, inverse patterns, dropped low bits, whether
the code is centred, the bit polarity and the projector resolution. :func:`reconstruct_captures`
reads the frames in that order, puts them in the order the gray-code coding expects, decodes,
triangulates with the given calibration (a ``calibration.json`` or an OpenCV ``.xml``/``.yml``
file such as SLStudio's) and writes the cloud **in the camera frame** (mm) into a new output
directory, with a report, previews and — when a reference cloud is given — the distance
statistics against it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dotshell.errors import CalibrationError
from dotshell.run.capture_layouts import load_layout, read_sequence
from dotshell.run.layout import RunLayout

if TYPE_CHECKING:  # numpy, OpenCV and the calibration readers load when captures are read
    import numpy as np

    from dotshell.geometry.calibration import RigCalibration


@dataclass
class CapturesResult:
    out_dir: Path
    report: dict[str, Any]


def reconstruct_captures(captures: Path | str, calibration: Path | str, layout_file: Path | str,
                         pm, out_dir: Path | str = "runs", reference: Path | str | None = None,
                         processing: dict[str, Any] | None = None, previews: bool = True,
                         coverage_radius_mm: float = 1.0) -> CapturesResult:
    """Decode and triangulate one foreign capture sequence; see the module docstring."""
    from dotshell.geometry.opencv_io import load_any_calibration
    from dotshell.run.ply import write_ply
    from dotshell.run.store import RunStore

    layout = load_layout(layout_file)
    calib = load_any_calibration(calibration)
    ref_points = None
    if reference is not None:  # checked before anything is written
        from dotshell.geometry.cloud_compare import load_reference_cloud

        ref_points = load_reference_cloud(reference)
    if tuple(calib.projector.size) != layout.projector_size:
        raise CalibrationError(
            f"the calibration's projector is {calib.projector.width}x{calib.projector.height} px "
            f"but layout {layout.name!r} says {layout.projector_size[0]}x"
            f"{layout.projector_size[1]} px; set projector_width/height in {layout.source} to "
            "the projector the frames were made with.")
    t0 = time.perf_counter()
    seq = read_sequence(captures, layout, pm)
    frames = seq.frames
    if seq.camera_size != calib.camera.size:
        w, h = seq.camera_size
        raise CalibrationError(
            f"{captures}: frames are {w}x{h} px but the calibration's camera "
            f"({calibration}) is {calib.camera.width}x{calib.camera.height} px; use the "
            "calibration of the camera that took these frames.")
    t1 = time.perf_counter()
    corr = seq.coding.decode(frames, layout.projector_size)
    t2 = time.perf_counter()
    proc = {"min_ray_angle_deg": 5.0, "row_tolerance_px": 1.5, **(processing or {})}
    # here, not at the top: the triangulation's compiled loops (numba, ~1 s to import) are for
    # reconstructing only
    from dotshell.pipeline.decode_quality import view_quality
    from dotshell.pipeline.reconstruct import no_points_error, triangulate_correspondence

    _, points, stats = triangulate_correspondence(corr, calib, proc)
    t3 = time.perf_counter()
    quality = view_quality(corr)
    t_quality = time.perf_counter() - t3
    if len(points) == 0:
        raise no_points_error(str(captures), {**corr.stats, **stats}, calib, corr.row is not None,
                              proc["min_ray_angle_deg"])
    store = RunStore.create(Path(out_dir), f"captures-{layout.name}")
    write_ply(store.path(RunLayout.CLOUD), points)
    calib.save(store.path(RunLayout.CALIBRATION))
    report: dict[str, Any] = {
        "captures": str(Path(captures).resolve()), "layout": layout.source,
        "calibration": calib.source, "frame": "camera (mm)",
        "decode": corr.stats, **stats, "quality": quality,
        "cloud": {"path": RunLayout.CLOUD, "points": int(len(points))},
    }
    if ref_points is not None:
        from dotshell.geometry.cloud_compare import compare_clouds

        report["reference"] = {"path": str(reference), **compare_clouds(
            points, ref_points, coverage_radius_mm)}
    t4 = time.perf_counter()
    if previews:
        report["previews"] = _previews(store, frames[0], corr, calib, points, layout.name, report)
    report["timings_s"] = {"read": round(t1 - t0, 3), "decode": round(t2 - t1, 3),
                           "triangulate": round(t3 - t2, 3), "quality": round(t_quality, 4),
                           "compare": round(t4 - t3 - t_quality, 3)}
    store.write_json(RunLayout.REPORT, report)
    return CapturesResult(store.root, report)


def _previews(store, white: np.ndarray, corr, calib: RigCalibration, points: np.ndarray,
              name: str, report: dict[str, Any]) -> dict[str, str]:
    from dotshell.render.previews import column_map_preview, frame_preview

    pdir = store.path(RunLayout.PREVIEWS)
    pdir.mkdir(exist_ok=True)
    out = {"frame": frame_preview(white, pdir / "frame.png"),
           "columns": column_map_preview(corr.column, corr.valid, calib.projector.width,
                                         pdir / "columns.png")}
    try:
        out["cloud"] = camera_view_preview(points, pdir / "cloud.png",
                                           f"{name}: {len(points)} points (camera frame)")
    except Exception as exc:  # 3-D rendering depends on the machine's OpenGL
        report["preview_warning"] = f"cloud preview skipped ({type(exc).__name__}: {exc})"
    return {k: str(Path(p).relative_to(store.root)) for k, p in out.items()}


def camera_view_preview(points: np.ndarray, path: Path, title: str) -> Path:
    """Render a camera-frame cloud (mm) as seen from a little beside the camera, coloured by
    depth (2nd–98th percentile), drawn by :mod:`dotshell.render.raster`."""
    import numpy as np

    from dotshell.render.previews import cloud_preview

    pts = np.asarray(points, np.float32)
    lo, hi = np.percentile(pts[:, 2], [2, 98])
    keep = (pts[:, 2] >= lo - 0.1 * (hi - lo)) & (pts[:, 2] <= hi + 0.1 * (hi - lo))
    centre = np.median(pts[keep], axis=0)
    eye = centre + np.array([0.35, -0.2, -1.0]) * float(np.linalg.norm(centre)) * 0.6
    return cloud_preview(pts[keep], pts[keep, 2], path, title, "depth z [mm]",
                         clim=(float(lo), float(hi)),
                         camera=[tuple(eye), tuple(centre), (0.0, -1.0, 0.0)])
