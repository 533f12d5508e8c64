"""Binary little-endian PLY point clouds: ``x y z`` (float32, mm) plus optional float32 scalar
properties (e.g. ``view``, ``nx ny nz``). Readable by open3d, MeshLab, CloudCompare, pyvista."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dotshell.errors import RunError
from dotshell.store import atomic_write_bytes


def write_ply(path: Path, points: np.ndarray, **scalars: np.ndarray) -> Path:
    """Write points (N, 3) and named per-point scalars (N,) atomically."""
    pts = np.asarray(points, np.float32).reshape(-1, 3)
    names = ["x", "y", "z", *scalars]
    cols = [pts[:, 0], pts[:, 1], pts[:, 2], *(np.asarray(v, np.float32).ravel()
                                                for v in scalars.values())]
    rec = np.empty(len(pts), dtype=[(n, "<f4") for n in names])
    for n, c in zip(names, cols):
        rec[n] = c
    header = ["ply", "format binary_little_endian 1.0", "comment dotshell, units mm",
              f"element vertex {len(pts)}", *(f"property float {n}" for n in names), "end_header"]
    atomic_write_bytes(Path(path), ("\n".join(header) + "\n").encode("ascii") + rec.tobytes())
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
