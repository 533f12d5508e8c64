"""Off-screen previews written as PNG into the run: a captured frame, the decoded column map in
false colour, and the merged cloud (pyvista, rendered without a display).

Rendering 3-D needs OpenGL; without a display we select VTK's EGL window (mesa). If that is
impossible the cloud preview is skipped with a warning naming the reason — never a crash.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from dotshell.run.layout import RunLayout
from dotshell.run.store import atomic_write_bytes


#: points drawn in a cloud preview (a fixed-seed random subset of larger clouds)
PREVIEW_POINTS = 300_000  # fills a 900 px image; VTK holds ~250 bytes a point (1 M: +180 MB)


def _write_png(path: Path, image: np.ndarray) -> Path:
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise ValueError(f"cannot encode {path}")
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


def _prepare_offscreen() -> None:
    if not os.environ.get("DISPLAY"):
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


def import_renderer() -> None:
    """Import pyvista's plotting (with VTK and matplotlib, ~2 s of CPU on 2 cores). Workflows
    call it in the background while the cloud is merged and validated
    (:func:`dotshell.pipeline.steps.import_ahead`); renderers call it before using pyvista: an
    import statement waits for a module another thread is importing, where pyvista's lazy
    attributes (``pv.Plotter``) would fail on a half-imported ``pyvista.plotting``."""
    _prepare_offscreen()
    import pyvista.plotting  # noqa: F401


def preview_pick(n: int) -> np.ndarray | slice:
    """Which of ``n`` points a cloud preview draws: a fixed-seed random :data:`PREVIEW_POINTS`
    of larger clouds (indices), else all (a slice)."""
    if n > PREVIEW_POINTS:  # a 900 px image shows no more; VTK copies are large
        return np.random.default_rng(0).choice(n, PREVIEW_POINTS, replace=False)
    return slice(None)


def cloud_preview(points: np.ndarray, scalars: np.ndarray | None, path: Path,
                  title: str = "", scalar_name: str = "z [mm]",
                  clim: tuple[float, float] | None = None, cmap: str = "viridis",
                  camera: list[tuple[float, float, float]] | None = None) -> Path:
    """Render a point cloud (mm) to PNG off-screen with pyvista; ``clim`` clips the colours.

    ``camera``: (eye, focal point, view-up) to look along, zoomed to fit the cloud, with
    eye-dome lighting (for single-view clouds); default an isometric view with axes."""
    import_renderer()  # waits for the import if another thread is making it (import_ahead)
    import pyvista as pv

    if len(points) > PREVIEW_POINTS:  # a 900 px image shows no more; VTK copies are large
        pick = preview_pick(len(points))
        points = points[pick]
        scalars = None if scalars is None else np.asarray(scalars)[pick]
    cloud = pv.PolyData(np.asarray(points, np.float32))
    pl = pv.Plotter(off_screen=True, window_size=[900, 900])
    try:
        pl.set_background("white")
        cloud[scalar_name] = np.asarray(points[:, 2] if scalars is None else scalars, np.float64)
        pl.add_mesh(cloud, scalars=scalar_name, point_size=2, render_points_as_spheres=False,
                    cmap=cmap, clim=clim, scalar_bar_args={"color": "black"})
        if title:
            pl.add_text(title, font_size=10, color="black")
        if camera is None:
            pl.camera_position = "iso"
            pl.camera.azimuth = 30
            pl.show_axes()
        else:
            pl.camera_position = camera
            pl.reset_camera()  # same viewing direction, the whole cloud in the picture
            pl.enable_eye_dome_lighting()
        screenshot(pl, Path(path))
    finally:
        pl.close()
    return Path(path)


def screenshot(plotter, path: Path) -> Path:
    """Render ``plotter`` to ``path`` (PNG) through a temporary file of this process only and a
    rename, so two processes never share a temporary name and a reader never sees half a PNG."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}-{threading.get_ident()}.tmp.png")
    try:
        plotter.screenshot(str(tmp))  # created as any file: the umask decides its mode
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def cloud_previews(store, points: np.ndarray, profile, bus) -> dict[str, Any]:
    """``previews/cloud.png`` of the merged cloud (``points`` (N, 3) mm, float32 or float64;
    by radius error for a cylinder, by height otherwise); returns {name: path relative to the
    run's products} and warns if skipped."""
    out: dict[str, Any] = {}
    store.path(RunLayout.PREVIEWS).mkdir(parents=True, exist_ok=True)
    v = profile.validation
    style: dict[str, Any] = {}
    drawn = preview_pick(len(points))  # the points drawn, picked before the colour scale is
    # taken over all of them in place (no second cloud-sized float64 array; issue 33)
    if v.shape == "cylinder":  # float64 arithmetic on float32 or float64 points (mm)
        scal, name = np.hypot(points[:, 0], points[:, 1], dtype=np.float64), "radius error [mm]"
        scal -= v.radius_mm
        shown = np.array(scal[drawn])  # the drawn points' colours (a copy)
        # the colour scale's cap (it saturates) from all the points' |r - R|, taken in place
        c = max(0.01, 4 * float(np.median(np.abs(scal, out=scal), overwrite_input=True)))
        scal = shown
        style = {"clim": (-c, c), "cmap": "coolwarm"}
    else:
        scal, name = points[drawn, 2], "z [mm]"
    points = points[drawn]
    try:
        out["cloud"] = cloud_preview(points, scal, store.path(RunLayout.preview("cloud")),
                                     f"{profile.name}: {len(points)} points", name, **style)
    except Exception as exc:  # rendering depends on the machine's OpenGL; degrade, don't crash
        bus.warn(f"cloud preview skipped: 3-D rendering is not available here "
                 f"({type(exc).__name__}: {exc}). The cloud is in cloud.ply.")
    return {k: str(Path(p).relative_to(store.root)) for k, p in out.items()}
