"""PLY point clouds. dotshell writes binary little-endian PLY: ``x y z`` (float32, mm) plus
optional float32 scalar properties (e.g. ``view``, ``nx ny nz``), readable by open3d, MeshLab,
CloudCompare, pyvista. It reads any PLY point cloud through plyfile (binary or ASCII, float or
double, extra properties such as colours): a reference cloud from open3d or MeshLab as well as
its own. benchmarks/ply_read.py measures the readers (docs/formats.md)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dotshell.errors import RunError
from dotshell.store import atomic_write_bytes


def write_ply(path: Path, points: np.ndarray, **scalars: np.ndarray) -> Path:
    """Write points (N, 3) and named per-point scalars (N,) atomically. The file's bytes are
    built once, in place (a 5 M-point cloud is 80 MB; no copies of it)."""
    points = np.asarray(points).reshape(-1, 3)
    names = ["x", "y", "z", *scalars]
    header = "\n".join(["ply", "format binary_little_endian 1.0", "comment dotshell, units mm",
                        f"element vertex {len(points)}", *(f"property float {n}" for n in names),
                        "end_header"]).encode("ascii") + b"\n"
    dtype = np.dtype([(n, "<f4") for n in names])
    data = np.empty(len(header) + len(points) * dtype.itemsize, np.uint8)
    data[:len(header)] = np.frombuffer(header, np.uint8)
    rec = data[len(header):].view(dtype)
    for i, n in enumerate("xyz"):
        rec[n] = points[:, i]
    for n, v in scalars.items():
        rec[n] = np.asarray(v).ravel()
    atomic_write_bytes(Path(path), data)
    return Path(path)


def read_ply(path: Path, finite: bool = True,
             float_type: type = np.float64) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Read a PLY point cloud: (points (N, 3) in the file's units — mm for dotshell's —
    float64, or ``float_type``; the vertices' other scalar properties by name, float64).

    Read by plyfile: binary (either byte order) or ASCII, ``float`` or ``double`` coordinates
    (open3d writes double), any other vertex properties (colours, normals, ``view``) and other
    elements (a mesh's faces, ignored). A file that is not such a PLY — no vertex element or no
    x, y, z, data cut short, non-finite points (unless ``finite`` is False, for clouds made
    elsewhere) — raises :class:`RunError` naming the file and what is wrong with it."""
    path = Path(path)
    if not path.exists():
        raise RunError(f"point cloud {path} is missing.")
    if path.is_dir():
        raise RunError(f"point cloud {path} is a directory, not a PLY file.")
    vertex = _vertex_data(path)
    names = vertex.dtype.names or ()
    if not {"x", "y", "z"} <= set(names):
        raise _damaged(path, f"its vertex properties {list(names)} need x, y, z")
    pts = np.empty((len(vertex), 3), dtype=float_type)
    for i, axis in enumerate("xyz"):
        pts[:, i] = vertex[axis]
    if finite and not np.isfinite(pts).all():
        bad = int((~np.isfinite(pts).all(axis=1)).sum())
        raise _damaged(path, f"{bad} of its {len(pts)} points have non-finite coordinates (NaN "
                             "or infinity)")
    scalars = {m: np.asarray(vertex[m], dtype=np.float64) for m in names
               if m not in ("x", "y", "z") and vertex.dtype[m].shape == ()
               and vertex.dtype[m].kind in "fiub"}
    return pts, scalars


def _vertex_data(path: Path) -> np.ndarray:
    """The structured array of the PLY's vertex element. Binary files are memory-mapped
    copy-on-write (plyfile's fast path: 2 M points in ~30 ms, where reading them through a
    stream took 20 s, benchmarks/ply_read.py); callers copy what they keep, and dotshell
    replaces files by renaming, so the mapped file never changes under the map."""
    from plyfile import PlyData

    with path.open("rb") as f:
        if f.read(4) != b"ply\n":
            raise RunError(f"{path} is not a PLY file (it does not start with 'ply'); give a "
                           "point cloud written by dotshell, open3d, MeshLab or CloudCompare.")
        f.seek(0)
        try:
            ply = PlyData.read(f, mmap="c")
        except MemoryError:
            raise _damaged(path, "its header declares more vertices than fit in memory") from None
        except Exception as exc:  # plyfile's parse errors, and numpy's on garbage input
            raise _damaged(path, f"{type(exc).__name__}: {exc}") from None
    if "vertex" not in ply:
        raise _damaged(path, f"it has no vertex element (elements: "
                             f"{[e.name for e in ply.elements]})")
    return ply["vertex"].data


def _damaged(path: Path, what: str) -> RunError:
    return RunError(f"{path} is not a point cloud dotshell can read: {what}. Make it again "
                    "(`dotshell reconstruct RUN` remakes a run's clouds from its frames) or "
                    "export it as a PLY with x, y, z vertex properties.")
