"""Binary little-endian PLY point clouds: ``x y z`` (float32, mm) plus optional float32 scalar
properties (e.g. ``view``, ``nx ny nz``). Readable by open3d, MeshLab, CloudCompare, pyvista."""

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


def read_ply(path: Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Read a PLY written by :func:`write_ply`: (points (N, 3) float64, scalars by name)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise RunError(f"point cloud {path} is missing.") from None
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply") or end < 0:
        raise RunError(f"{path} is not a PLY file.")
    header = data[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise RunError(f"{path}: only binary little-endian PLY is supported.")
    n = next(int(h.split()[2]) for h in header if h.startswith("element vertex"))
    names = [h.split()[2] for h in header if h.startswith("property float")]
    rec = np.frombuffer(data[end + len(b"end_header\n"):], dtype=[(m, "<f4") for m in names],
                        count=n)
    pts = np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(np.float64)
    return pts, {m: rec[m].astype(np.float64) for m in names if m not in ("x", "y", "z")}
