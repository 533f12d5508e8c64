"""PLY point clouds. dotshell writes binary little-endian PLY: ``x y z`` (float32, mm) plus
optional float32 scalar properties (e.g. ``view``, ``nx ny nz``), readable by open3d, MeshLab,
CloudCompare, pyvista. It reads any PLY point cloud through plyfile (binary or ASCII, float or
double, extra properties such as colours): a reference cloud from open3d or MeshLab as well as
its own. benchmarks/ply_read.py measures the readers (docs/formats.md)."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from dotshell.errors import RunError
from dotshell.run.store import atomic_write_bytes


def ply_buffer(n_points: int, scalar_names: Sequence[str] = ()) -> tuple[np.ndarray,
                                                                         np.ndarray]:
    """A binary PLY file of ``n_points`` points in memory, to be filled in place: (its bytes
    as a uint8 array, header written; its records as an (N, 3 + len(scalar_names)) float32
    view of them: x, y, z, then the scalars in order). Write it with
    :func:`~dotshell.run.store.atomic_write_bytes`."""
    names = ["x", "y", "z", *scalar_names]
    header = "\n".join(["ply", "format binary_little_endian 1.0", "comment dotshell, units mm",
                        f"element vertex {n_points}", *(f"property float {n}" for n in names),
                        "end_header"]).encode("ascii") + b"\n"
    data = np.empty(len(header) + n_points * 4 * len(names), np.uint8)
    data[:len(header)] = np.frombuffer(header, np.uint8)
    return data, data[len(header):].view("<f4").reshape(n_points, len(names))


def write_ply(path: Path, points: np.ndarray, **scalars: np.ndarray) -> Path:
    """Write points (N, 3) and named per-point scalars (N,) atomically. The file's bytes are
    built once, in place, and written from there (a 5 M-point cloud is 80 MB; no copies)."""
    points = np.asarray(points).reshape(-1, 3)
    data, rec = ply_buffer(len(points), list(scalars))
    rec[:, :3] = points
    for i, v in enumerate(scalars.values(), 3):
        rec[:, i] = np.asarray(v).ravel()
    atomic_write_bytes(Path(path), data.data)  # the array's memoryview: no copy
    return Path(path)


def point_count(path: Path) -> int:
    """The number of points of the PLY at ``path`` (its data mapped, not read; RunError naming
    the file if it is not a point cloud dotshell can read)."""
    return len(_cloud_vertices(Path(path)))


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
    vertex = _cloud_vertices(path)
    names = vertex.dtype.names or ()
    pts: np.ndarray = np.empty((len(vertex), 3), dtype=float_type)
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


def map_ply(path: Path, chunk: int = 1 << 20) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """:func:`read_ply` without copies, for clouds too large to copy: the points (N, 3) and
    the scalar properties as views of the file's memory map, in the file's types (float32 for
    dotshell's), where the file is binary with x, y, z of one type side by side (dotshell's,
    open3d's); copies otherwise. Non-finite points raise :class:`RunError` (checked ``chunk``
    points at a time). The mesh stage reads an 8.3 M-point cloud so: 133 MB of mapped file
    pages instead of 300 MB of float64 copies (docs/performance.md)."""
    from numpy.lib.recfunctions import structured_to_unstructured

    path = Path(path)
    vertex = _cloud_vertices(path)
    names = vertex.dtype.names or ()
    pts = structured_to_unstructured(vertex[["x", "y", "z"]], copy=False)
    bad = sum(_non_finite_rows(pts[s:s + chunk]) for s in range(0, len(pts), chunk))
    if bad:
        raise _damaged(path, f"{bad} of its {len(pts)} points have non-finite coordinates (NaN "
                             "or infinity)")
    scalars = {m: vertex[m] for m in names if m not in ("x", "y", "z")
               and vertex.dtype[m].shape == () and vertex.dtype[m].kind in "fiub"}
    return pts, scalars


def _non_finite_rows(points: np.ndarray) -> int:
    """How many rows of ``points`` (N, 3) hold a NaN or infinity. All finite is found with a
    flat reduction first: the row-wise one over the mapped cloud (rows 16 bytes apart) took
    ~0.1 s of the mesh process's CPU for 5.5 M points, the flat one a quarter of it."""
    finite = np.isfinite(points)
    return 0 if finite.all() else int((~finite.all(axis=1)).sum())


def point_chunks(path: Path, chunk: int = 1 << 20) -> Iterator[np.ndarray]:
    """The points of the cloud at ``path`` as float64 arrays (n, 3), ``chunk`` points at a
    time, for a pass over a cloud too large to hold. A binary file is read chunk by chunk
    (the pages of a mapped file stay in the process's resident memory until it is unmapped:
    133 MB for the 8.3 M-point agar cloud, issue 33); other files through their map. Raises
    :class:`RunError` naming the file, as :func:`read_ply` does, where points are not finite
    (after the chunks before the first bad one)."""
    path = Path(path)
    vertex = _cloud_vertices(path)
    bad = 0
    for part in _vertex_chunks(path, vertex, chunk):
        pts = np.empty((len(part), 3))
        for i, axis in enumerate("xyz"):
            pts[:, i] = part[axis]
        bad += int((~np.isfinite(pts).all(axis=1)).sum())
        if not bad:
            yield pts
    if bad:
        raise _damaged(path, f"{bad} of its {len(vertex)} points have non-finite coordinates "
                             "(NaN or infinity)")


def _vertex_chunks(path: Path, vertex: np.ndarray, chunk: int) -> Iterator[Any]:
    """The vertex records ``chunk`` at a time: read from the file where ``vertex`` maps a
    binary file (its pages would stay resident), else slices of ``vertex``."""
    if isinstance(vertex, np.memmap) and vertex.offset is not None:
        offset, dtype = vertex.offset, vertex.dtype
        with path.open("rb") as f:
            for start in range(0, len(vertex), chunk):
                f.seek(offset + start * dtype.itemsize)
                yield np.fromfile(f, dtype, min(chunk, len(vertex) - start))
    else:
        for start in range(0, len(vertex), chunk):
            yield vertex[start:start + chunk]


def _cloud_vertices(path: Path) -> np.ndarray:
    """The vertex element of the point cloud at ``path``, which has x, y, z; RunError naming the
    file otherwise."""
    if not path.exists():
        raise RunError(f"point cloud {path} is missing.")
    if path.is_dir():
        raise RunError(f"point cloud {path} is a directory, not a PLY file.")
    vertex = _vertex_data(path)
    names = vertex.dtype.names or ()
    if not {"x", "y", "z"} <= set(names):
        raise _damaged(path, f"its vertex properties {list(names)} need x, y, z")
    return vertex


def _vertex_data(path: Path) -> np.ndarray:
    """The structured array of the PLY's vertex element. Binary files are memory-mapped
    copy-on-write (plyfile's fast path: 2 M points in ~30 ms, where reading them through a
    stream took 20 s, benchmarks/ply_read.py); callers copy what they keep, and dotshell
    replaces files by renaming, so the mapped file never changes under the map."""
    from plyfile import PlyData, PlyElementParseError, PlyHeaderParseError

    with path.open("rb") as f:
        lines = _header_lines(path, f.read(HEADER_MAX))
        f.seek(0)
        try:
            ply = PlyData.read(f, mmap="c")
        except PlyHeaderParseError as exc:
            where = f" line {exc.line} ({lines[exc.line - 1]!r})" if exc.line else ""
            raise _damaged(path, f"its header{where} is wrong: {exc.message}") from None
        except PlyElementParseError as exc:
            raise _damaged(path, _early_end(lines, exc)) from None
        except (UnicodeDecodeError, ValueError) as exc:
            if "format ascii 1.0" in lines:
                raise _damaged(path, "its data is not the text its header's 'format ascii' "
                                     f"announces ({exc})") from None
            raise _damaged(path, f"{type(exc).__name__}: {exc}") from None
        except MemoryError:
            raise _damaged(path, "its header declares more vertices than fit in memory") from None
        except Exception as exc:  # plyfile and numpy on other garbage: named, never a traceback
            raise _damaged(path, f"{type(exc).__name__}: {exc}") from None
    if "vertex" not in ply:
        raise _damaged(path, f"it has no vertex element (elements: "
                             f"{[e.name for e in ply.elements]})")
    return ply["vertex"].data


#: the longest PLY header read (bytes); dotshell's, open3d's and MeshLab's take a few hundred
HEADER_MAX = 1 << 16


def _header_lines(path: Path, head: bytes) -> list[str]:
    """The header's lines (``ply`` ... up to ``end_header``), or RunError."""
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        raise RunError(f"{path} is not a PLY file (no 'ply' ... 'end_header' header); give a "
                       "point cloud written by dotshell, open3d, MeshLab or CloudCompare.")
    try:
        return [ln.strip() for ln in head[:end].decode("ascii").splitlines()]
    except UnicodeDecodeError:
        raise _damaged(path, "its header is not ASCII text") from None


def _early_end(lines: list[str], exc: Exception) -> str:
    """What a data error means: the file ends before the vertices its header declares."""
    count, props, in_vertex = "?", [], False
    for line in lines:
        words = line.split()
        if words[:1] == ["element"]:
            in_vertex = words[1:2] == ["vertex"]
            if in_vertex and len(words) > 2:
                count = words[2]
        elif words[:1] == ["property"] and in_vertex:
            props.append(" ".join(words[1:]))
    row = getattr(exc, "row", None)
    got = f"after {row} of the {count} vertices" if row is not None else "early"
    return (f"the data ends {got} its header declares ({getattr(exc, 'message', exc)}): the "
            f"file is cut short, or the header's vertex count or property types "
            f"({', '.join(props)}) do not match the data")


def _damaged(path: Path, what: str) -> RunError:
    return RunError(f"{path} is not a point cloud dotshell can read: {what}. Make it again "
                    "(`dotshell reconstruct RUN` remakes a run's clouds from its frames) or "
                    "export it as a PLY with x, y, z vertex properties.")
