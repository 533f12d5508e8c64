"""Previews written as PNG into the run: a captured frame, the decoded column map in false
colour, and the merged cloud (drawn by :mod:`dotshell.render.raster`: numpy and OpenCV, no
display or OpenGL needed). A preview that cannot be made is skipped with a warning naming the
reason — never a crash.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

import dotshell.render.raster as raster
from dotshell.run.layout import RunLayout
from dotshell.run.store import atomic_write_bytes


#: points drawn in a cloud preview (every k-th point of larger clouds)
PREVIEW_POINTS = 300_000  # fills a 900 px image


def _write_png(path: Path, image: np.ndarray) -> Path:
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise ValueError(f"cannot encode {path}")
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, buf.tobytes())
    return path


def frame_preview(frame: np.ndarray, path: Path) -> Path:
    """A captured frame stretched to 8 bits (0.5 and 99.5 percentiles)."""
    f = frame.astype(np.float32)
    lo, hi = np.percentile(f, [0.5, 99.5])
    img = np.clip((f - lo) / max(hi - lo, 1e-6) * 255, 0, 255).astype(np.uint8)
    return _write_png(path, img)


def column_map_preview(column: np.ndarray, valid: np.ndarray, width: int, path: Path) -> Path:
    """Decoded projector columns in false colour (turbo); undecoded pixels black."""
    norm = np.zeros(column.shape, np.uint8)
    norm[valid] = np.clip(column[valid] / max(width - 1, 1) * 255, 0, 255).astype(np.uint8)
    img = cv2.applyColorMap(norm, cv2.COLORMAP_TURBO)
    img[~valid] = 0
    return _write_png(path, img)


def cloud_preview(points: np.ndarray, scalars: np.ndarray | None, path: Path,
                  title: str = "", scalar_name: str = "z [mm]",
                  clim: tuple[float, float] | None = None, cmap: str = "viridis",
                  camera: list[tuple[float, float, float]] | None = None) -> Path:
    """Draw a point cloud (mm) to a 900×900 PNG, coloured by ``scalars`` (default: z) over
    ``clim`` (default: their range; clipped at its ends), with a colour bar
    (:mod:`dotshell.render.raster`, no OpenGL).

    ``camera``: (eye, focal point, view-up) to look along, the whole cloud in the picture;
    default the isometric view with the sample frame's axes."""
    pts = np.asarray(points)
    values = pts[:, 2] if scalars is None else np.asarray(scalars)
    if len(pts) > PREVIEW_POINTS:  # a 900 px image shows no more: every k-th point
        step = -(-len(pts) // PREVIEW_POINTS)
        pts, values = pts[::step], values[::step]
    values = np.asarray(values, np.float64)
    if clim is None:
        clim = (float(values.min()), float(values.max())) if len(values) else (0.0, 1.0)
    view = None if camera is None else raster.Camera.looking(
        np.subtract(camera[1], camera[0]), camera[2])
    canvas = raster.Canvas(camera=view, right_margin=110)
    if len(pts):
        canvas.fit(pts)
        raster.draw_points(canvas, pts, raster.scalar_colours(values, clim, cmap))
    raster.draw_colour_bar(canvas, clim, cmap, scalar_name)
    if title:
        raster.draw_title(canvas, title)
    if camera is None:
        raster.draw_axes(canvas)
    return _write_png(Path(path), canvas.image)


def cloud_previews(store, points: np.ndarray, profile, bus) -> dict[str, Any]:
    """``previews/cloud.png`` of the merged cloud (``points`` (N, 3) mm, float32 or float64;
    by radius error for a cylinder, by height otherwise); returns {name: path relative to the
    run's products} and warns if skipped."""
    out: dict[str, Any] = {}
    store.path(RunLayout.PREVIEWS).mkdir(parents=True, exist_ok=True)
    n = len(points)
    if n > PREVIEW_POINTS:  # the points drawn, and the colours computed for them only
        points = points[::-(-n // PREVIEW_POINTS)]
    v = profile.validation
    style: dict[str, Any] = {}
    if v.shape == "cylinder":  # float64 arithmetic on float32 or float64 points (mm)
        scal, name = np.hypot(points[:, 0], points[:, 1], dtype=np.float64), "radius error [mm]"
        scal -= v.radius_mm
        # the colour scale: 4x the median |error| of the points drawn, at least 0.01 mm
        c = max(0.01, 4 * float(np.median(np.abs(scal), overwrite_input=True)))
        style = {"clim": (-c, c), "cmap": "coolwarm"}
    else:
        scal, name = points[:, 2], "z [mm]"
    try:
        out["cloud"] = cloud_preview(points, scal, store.path(RunLayout.preview("cloud")),
                                     f"{profile.name}: {n} points", name, **style)
    except Exception as exc:  # a preview is never worth a failed step
        bus.warn(f"cloud preview skipped ({type(exc).__name__}: {exc}). The cloud is in "
                 "cloud.ply.")
    return {k: str(Path(p).relative_to(store.root)) for k, p in out.items()}
