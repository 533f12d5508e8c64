"""Off-screen PNG previews of a mesh directory: the closed surface with its edges, and the
tetrahedral volume cut in half (pyvista; EGL when there is no display)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from dotshell.fem.meshfiles import read_surface, read_volume
from dotshell.run.layout import RunLayout


def _plotter():
    if not os.environ.get("DISPLAY"):
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista as pv

    pl = pv.Plotter(off_screen=True, window_size=[900, 900])
    pl.set_background("white")
    return pv, pl


def _shoot(pl, path: Path, title: str) -> Path:
    pl.add_text(title, font_size=10, color="black")
    pl.camera_position = "iso"
    pl.camera.azimuth = 30
    pl.show_axes()
    from dotshell.render.previews import screenshot

    return screenshot(pl, path)


def render_mesh_previews(mesh_dir: Path, out_dir: Path, suffix: str = "") -> dict[str, Path]:
    """``surface{suffix}.png`` and ``volume{suffix}.png`` in ``out_dir``."""
    mesh_dir, out_dir = Path(mesh_dir), Path(out_dir)
    out: dict[str, Path] = {}
    surf = read_surface(mesh_dir / RunLayout.SURFACE)
    pv, pl = _plotter()
    try:
        faces = np.hstack([np.full((len(surf.triangles), 1), 3), surf.triangles]).ravel()
        pl.add_mesh(pv.PolyData(surf.vertices, faces), color="lightsteelblue", show_edges=True,
                    edge_color="black", line_width=0.5)
        out["surface"] = _shoot(pl, out_dir / f"surface{suffix}.png",
                                f"surface: {len(surf.vertices)} nodes, "
                                f"{len(surf.triangles)} triangles")
    finally:
        pl.close()
    vol = read_volume(mesh_dir / RunLayout.VOLUME)
    pv, pl = _plotter()
    try:
        cells = np.hstack([np.full((len(vol.tets), 1), 4), vol.tets]).ravel()
        grid = pv.UnstructuredGrid(cells, np.full(len(vol.tets), pv.CellType.TETRA), vol.nodes)
        centre = vol.nodes.mean(axis=0)
        half = grid.extract_cells(np.nonzero(grid.cell_centers().points[:, 1] <= centre[1])[0])
        pl.add_mesh(half, color="wheat", show_edges=True, edge_color="black", line_width=0.3)
        out["volume"] = _shoot(pl, out_dir / f"volume{suffix}.png",
                               f"volume (cut at y = {centre[1]:.1f} mm): {len(vol.nodes)} nodes, "
                               f"{len(vol.tets)} tetrahedra")
    finally:
        pl.close()
    return out
