"""Common mesh formats through meshio: the volume mesh as VTU, legacy VTK, Gmsh 4.1 or Medit,
the closed surface as STL, PLY or OBJ (all mm)."""

from __future__ import annotations

from pathlib import Path

from dotshell.fem.meshfiles import _atomic_meshio, read_surface, read_volume

#: format name → (file name, meshio format, which mesh)
FORMATS: dict[str, tuple[str, str, str]] = {
    "vtu": ("volume.vtu", "vtu", "volume"),
    "vtk": ("volume.vtk", "vtk", "volume"),
    "gmsh": ("volume.msh", "gmsh", "volume"),
    "medit": ("volume.mesh", "medit", "volume"),
    "stl": ("surface.stl", "stl", "surface"),
    "ply": ("surface.ply", "ply", "surface"),
    "obj": ("surface.obj", "obj", "surface"),
}


def write_common(mesh_dir: Path, out_dir: Path, formats: list[str]) -> list[Path]:
    """Convert the mesh directory's ``volume.vtu`` / ``surface.ply`` into ``formats``."""
    import meshio
    import numpy as np

    volume = read_volume(mesh_dir / "volume.vtu") if any(
        FORMATS[f][2] == "volume" for f in formats) else None
    surface = read_surface(mesh_dir / "surface.ply") if any(
        FORMATS[f][2] == "surface" for f in formats) else None
    out = []
    for f in formats:
        name, fmt, which = FORMATS[f]
        if which == "volume":
            point_data = {k: np.asarray(v, float) for k, v in volume.point_data.items()}
            point_data["boundary"] = volume.boundary_nodes.astype(float)
            m = meshio.Mesh(volume.nodes, [("tetra", volume.tets)],
                            point_data=point_data if fmt in ("vtu", "vtk") else {})
        else:
            # int32 indices: PLY has no 64-bit integers, and meshio prints a warning of its
            # own (not a Python warning) on stderr when it casts them down
            m = meshio.Mesh(surface.vertices, [("triangle", surface.triangles.astype(np.int32))])
        kwargs = {"binary": False} if fmt in ("stl", "gmsh") else {}
        out.append(_atomic_meshio(Path(out_dir) / name, m, fmt, **kwargs))
    return out
