"""dotshell.run.ply.read_ply as it was before issue 30 (commit 04737f4), frozen: the "before" side of
benchmarks/ply_read.py. Benchmarks only; nothing in the product imports it. It read binary
little-endian float PLY only. Its write_ply is left out (unchanged in dotshell.run.ply).

The original module docstring follows.

Binary little-endian PLY point clouds: ``x y z`` (float32, mm) plus optional float32 scalar
properties (e.g. ``view``, ``nx ny nz``). Readable by open3d, MeshLab, CloudCompare, pyvista."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dotshell.errors import RunError


def read_ply(path: Path, finite: bool = True,
             float_type: type = np.float64) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Read a PLY written by :func:`write_ply`: (points (N, 3) float64, scalars by name);
    ``float_type=np.float32``: the points as stored, without widening them.

    Any other content — not a PLY, another format or property type, a header that does not
    match the data, non-finite points (unless ``finite`` is False, for clouds made elsewhere) —
    raises :class:`RunError` naming the file and what is wrong with it."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise RunError(f"point cloud {path} is missing.") from None
    except IsADirectoryError:
        raise RunError(f"point cloud {path} is a directory, not a PLY file.") from None
    names, n, body = _parse_header(path, data)
    dtype = np.dtype([(m, "<f4") for m in names])
    if len(body) < n * dtype.itemsize:
        raise _damaged(path, f"it holds {len(body)} bytes of vertex data, the header's {n} "
                             f"vertices need {n * dtype.itemsize}")
    rec = np.frombuffer(body, dtype=dtype, count=n)
    pts = np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(float_type, copy=False)
    if finite and not np.isfinite(pts).all():
        bad = int((~np.isfinite(pts).all(axis=1)).sum())
        raise _damaged(path, f"{bad} of its {n} points have non-finite coordinates (NaN or "
                             "infinity)")
    return pts, {m: rec[m].astype(np.float64) for m in names if m not in ("x", "y", "z")}


def _damaged(path: Path, what: str) -> RunError:
    return RunError(f"{path} is not a point cloud dotshell can read: {what}. Make it again "
                    "(`dotshell reconstruct RUN` remakes a run's clouds from its frames) or "
                    "export it as a binary little-endian PLY of float x, y, z.")


def _parse_header(path: Path, data: bytes) -> tuple[list[str], int, bytes]:
    """(property names, vertex count, the bytes after the header) of a binary PLY of one
    vertex element with float properties including x, y, z."""
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise RunError(f"{path} is not a PLY file (no 'ply' ... 'end_header' header); give a "
                       "point cloud written by dotshell, open3d, MeshLab or CloudCompare.")
    try:
        header = data[:end].decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise _damaged(path, "its header is not ASCII text") from None
    if "format binary_little_endian 1.0" not in header:
        fmt = next((h for h in header if h.startswith("format")), "no format line")
        raise _damaged(path, f"only binary little-endian PLY is supported, not {fmt!r}")
    n: int | None = None
    names: list[str] = []
    for line in header[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info", "format"):
            continue
        if words[0] == "element":
            if words[1:2] != ["vertex"] or n is not None:
                raise _damaged(path, f"only one vertex element is supported, found {line!r}")
            if len(words) != 3 or not words[2].isdigit():
                raise _damaged(path, f"the line {line!r} does not give a vertex count")
            n = int(words[2])
        elif words[0] == "property" and n is not None:
            if len(words) != 3 or words[1] != "float":
                raise _damaged(path, f"{line!r}: vertex properties must be 'property float NAME'")
            names.append(words[2])
        else:
            raise _damaged(path, f"unexpected header line {line!r}")
    if n is None:
        raise _damaged(path, "it has no 'element vertex N' line")
    if len(set(names)) != len(names) or not {"x", "y", "z"} <= set(names):
        raise _damaged(path, f"its vertex properties {names} need x, y, z, each once")
    return names, n, data[end + len(b"end_header\n"):]
