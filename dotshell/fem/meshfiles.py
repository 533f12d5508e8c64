"""The mesh files of a run directory (format in ``docs/formats.md``), written atomically:

* ``surface.ply`` — the closed triangle surface (binary PLY, mm, outward triangles);
* ``volume.vtu`` — the tetrahedral mesh (VTK XML unstructured grid, mm, positively oriented
  tetrahedra) with per-node arrays ``boundary`` (1 on the surface), ``region``,
  ``mua_per_mm``, ``musp_per_mm``, ``refractive_index``;
* ``optodes.json`` — source and detector positions (mm, sample frame) and the source–detector
  links (0-based), when the profile gives optodes.

Exporters and the forward solver read these; they never re-run a mesher.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dotshell.errors import RunError
from dotshell.fem.meshes import TetMesh, TriangleSurface
from dotshell.run.store import atomic_write_text, temp_beside

OPTICS = ("mua_per_mm", "musp_per_mm", "refractive_index")


def _atomic_meshio(path: Path, mesh, file_format: str, **kwargs) -> Path:
    import meshio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = temp_beside(path)  # the umask decides its permissions
    os.close(fd)
    try:
        meshio.write(tmp, mesh, file_format=file_format, **kwargs)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def _read_meshio(path: Path, what: str):
    import meshio

    path = Path(path)
    if not path.is_file():
        raise RunError(f"{path} is missing: {what}. Run `dotshell mesh RUN` first (or set "
                       "[mesh] after_scan = true in the profile).")
    if path.suffix.lower() == ".ply" and not _whole_ply_header(path):
        raise RunError(f"{path} cannot be read (no complete PLY header: 'ply' ... "
                       "'end_header'); re-run `dotshell mesh RUN`.")
    said = io.StringIO()
    try:  # meshio prints its reasons and calls sys.exit(1) for some damaged files
        with contextlib.redirect_stdout(said), contextlib.redirect_stderr(said):
            return meshio.read(path)
    except (Exception, SystemExit) as exc:  # many types for a damaged file
        why = " ".join(said.getvalue().split()) or f"{type(exc).__name__}: {exc}"
        raise RunError(f"{path} cannot be read ({why}); re-run `dotshell mesh RUN`.") from None


def _whole_ply_header(path: Path) -> bool:
    """A 'ply' line and an 'end_header' line: meshio's PLY reader loops for ever at the end of
    a file whose header never ends."""
    with open(path, "rb") as f:
        head = f.read(1 << 16)
    lines = [ln.strip() for ln in head.split(b"\n")]
    return bool(lines) and lines[0] == b"ply" and b"end_header" in lines


def write_surface(path: Path, surface: TriangleSurface) -> Path:
    import meshio

    # int32 indices: PLY has no 64-bit integers, and meshio prints its own warning (not a
    # Python warning) on the user's terminal when it casts them down
    mesh = meshio.Mesh(surface.vertices, [("triangle", np.asarray(surface.triangles, np.int32))])
    return _atomic_meshio(path, mesh, "ply", binary=True)


def _check_cells(path: Path, points: np.ndarray, cells: np.ndarray | None, kind: str,
                 corners: int) -> None:
    """Finite 3-D points and ``kind`` cells of ``corners`` valid point indices, or RunError."""
    why = ""
    if cells is None or len(cells) == 0:
        why = f"it holds no {kind}"
    elif points.ndim != 2 or points.shape[1] != 3 or not np.isfinite(points).all():
        why = "its points are not finite 3-D coordinates"
    elif cells.ndim != 2 or cells.shape[1] != corners or cells.min() < 0 or \
            cells.max() >= len(points):
        why = f"its {kind} refer to points that do not exist"
    if why:
        raise RunError(f"{path} is damaged: {why}; re-run `dotshell mesh RUN`.")


def read_surface(path: Path) -> TriangleSurface:
    m = _read_meshio(path, "the closed surface")
    tri = m.cells_dict.get("triangle")
    _check_cells(Path(path), np.asarray(m.points), tri, "triangles", 3)
    return TriangleSurface(m.points, tri)


def write_volume(path: Path, mesh: TetMesh) -> Path:
    import meshio

    data = {"boundary": mesh.boundary_nodes.astype(np.int32)}
    for k, v in mesh.point_data.items():
        data[k] = np.asarray(v)
    out = meshio.Mesh(mesh.nodes, [("tetra", mesh.tets)], point_data=data)
    return _atomic_meshio(path, out, "vtu")


def read_volume(path: Path) -> TetMesh:
    m = _read_meshio(path, "the tetrahedral volume mesh")
    tets = m.cells_dict.get("tetra")
    _check_cells(Path(path), np.asarray(m.points), tets, "tetrahedra", 4)
    pd = {k: np.asarray(v) for k, v in m.point_data.items() if k != "boundary"}
    bad = [k for k, v in pd.items() if len(v) != len(m.points)
           or (np.issubdtype(v.dtype, np.number) and not np.isfinite(v).all())]
    if bad:
        raise RunError(f"{path} is damaged: its node data {bad} do not give one finite value "
                       "per node; re-run `dotshell mesh RUN`.")
    return TetMesh(m.points, tets, pd)


@dataclass
class Optodes:
    """Sources and detectors (mm, sample frame) and links ``(source, detector)`` 0-based."""

    sources_mm: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))
    detectors_mm: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))
    links: np.ndarray = field(default_factory=lambda: np.empty((0, 2), np.int64))

    def __post_init__(self) -> None:
        self.sources_mm = np.asarray(self.sources_mm, float).reshape(-1, 3)
        self.detectors_mm = np.asarray(self.detectors_mm, float).reshape(-1, 3)
        self.links = np.asarray(self.links, np.int64).reshape(-1, 2)

    @property
    def empty(self) -> bool:
        return len(self.sources_mm) == 0 and len(self.detectors_mm) == 0


def optodes_from_settings(cfg: dict, where: str) -> Optodes:
    """Optodes from the profile's ``[mesh.optodes]`` (links default to every pair)."""
    from dotshell.errors import ProfileError

    for key in ("sources_mm", "detectors_mm"):
        bad = [r for r in cfg[key] if len(r) != 3]
        if bad:
            raise ProfileError(f"{where}: [mesh.optodes.{key}] rows must be [x, y, z] in mm; "
                               f"got {bad[0]!r}.")
    o = Optodes(cfg["sources_mm"], cfg["detectors_mm"])
    if cfg["links"]:
        links = np.asarray(cfg["links"], float)
        if links.ndim != 2 or links.shape[1] != 2 or (links != np.round(links)).any():
            raise ProfileError(f"{where}: [mesh.optodes.links] must be [[source, detector], ...] "
                               "with 0-based integer indices.")
        links = links.astype(np.int64)
        if (links < 0).any() or (links[:, 0] >= len(o.sources_mm)).any() or (
                links[:, 1] >= len(o.detectors_mm)).any():
            raise ProfileError(f"{where}: [mesh.optodes.links] refers to a source or detector "
                               f"that does not exist ({len(o.sources_mm)} sources, "
                               f"{len(o.detectors_mm)} detectors, 0-based).")
        o.links = links
    else:
        s, d = np.meshgrid(np.arange(len(o.sources_mm)), np.arange(len(o.detectors_mm)),
                           indexing="ij")
        o.links = np.column_stack([s.ravel(), d.ravel()])
    return o


def write_optodes(path: Path, optodes: Optodes) -> Path:
    atomic_write_text(Path(path), json.dumps({
        "units": "mm, sample frame; links are 0-based (source, detector)",
        "sources_mm": optodes.sources_mm.tolist(),
        "detectors_mm": optodes.detectors_mm.tolist(),
        "links": optodes.links.tolist(),
    }, indent=2))
    return Path(path)


def read_optodes(path: Path) -> Optodes:
    """The optodes of a mesh directory, or empty ones when it has no ``optodes.json``."""
    path = Path(path)
    if not path.is_file():
        return Optodes()
    try:
        d = json.loads(path.read_text())
        o = Optodes(d["sources_mm"], d["detectors_mm"], d["links"])
    except (ValueError, KeyError, TypeError, IndexError, OverflowError) as exc:  # JSON, shape, size
        raise RunError(f"{path} is not a valid optodes file ({type(exc).__name__}: {exc}); "
                       "make it again with `dotshell mesh RUN`.") from None
    n_s, n_d = len(o.sources_mm), len(o.detectors_mm)
    if not (np.isfinite(o.sources_mm).all() and np.isfinite(o.detectors_mm).all()) or (
            len(o.links) and ((o.links < 0).any() or (o.links[:, 0] >= n_s).any()
                              or (o.links[:, 1] >= n_d).any())):
        raise RunError(f"{path} is not a valid optodes file (non-finite positions or links to "
                       f"optodes that do not exist: {n_s} sources, {n_d} detectors); make it "
                       "again with `dotshell mesh RUN`.")
    return o
