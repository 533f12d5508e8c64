"""How the PLY reader was chosen: reading a 2 M-point cloud with dotshell's reader (plyfile
inside), the reader it replaced (benchmarks/ply_before.py), plyfile itself (with and without a
memory map) and open3d, in the same run (docs/formats.md, "Reading PLY").

Usage: ``.venv/bin/python benchmarks/ply_read.py [--points N] [--repeats R]``. Writes the cloud
as dotshell writes ``cloud.ply`` (binary float32 x y z + view) and as open3d writes one (binary
double, and ASCII double), then times each reader warm (page cache), median of R runs, and
checks that every reader returns the same points.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np

import ply_before
from dotshell.runtime.compat import import_open3d
from dotshell.run.ply import read_ply, write_ply


def _median_s(read: Callable[[], np.ndarray], repeats: int) -> tuple[float, np.ndarray]:
    times, pts = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        pts = read()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), pts


def _plyfile(path: Path, mmap: bool) -> np.ndarray:
    from plyfile import PlyData

    v = PlyData.read(str(path), mmap="c" if mmap else False)["vertex"].data
    return np.column_stack([v["x"], v["y"], v["z"]]).astype(np.float64)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=2_000_000)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    o3d = import_open3d()
    rng = np.random.default_rng(0)
    pts = (rng.normal(scale=20.0, size=(args.points, 3)) + [0, 0, 200]).astype(np.float32)
    with tempfile.TemporaryDirectory() as tmp:
        own = write_ply(Path(tmp) / "own.ply", pts, view=rng.integers(0, 12, args.points))
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.astype(np.float64)))
        o3d_bin, o3d_txt = Path(tmp) / "o3d.ply", Path(tmp) / "o3d-ascii.ply"
        o3d.io.write_point_cloud(str(o3d_bin), pcd)
        o3d.io.write_point_cloud(str(o3d_txt), pcd, write_ascii=True)
        cases = {
            "dotshell cloud.ply (binary float32 + view)": own,
            "open3d default (binary double)": o3d_bin,
            "open3d ASCII (double)": o3d_txt,
        }
        readers: dict[str, Callable[[Path], np.ndarray]] = {
            "dotshell.run.ply.read_ply (plyfile)": lambda p: read_ply(p)[0],
            "before (own binary parser)": lambda p: ply_before.read_ply(p)[0],
            "plyfile, memory map": lambda p: _plyfile(p, True),
            "plyfile, no memory map": lambda p: _plyfile(p, False),
            "open3d.io.read_point_cloud": lambda p: np.asarray(
                o3d.io.read_point_cloud(str(p)).points),
        }
        print(f"{args.points} points, median of {args.repeats} warm reads")
        for case, path in cases.items():
            print(f"\n{case}: {path.stat().st_size / 1e6:.0f} MB")
            ours = None
            for name, reader in readers.items():
                try:
                    slow = "ASCII" in case or "no memory map" in name  # seconds a read
                    s, got = _median_s(lambda: reader(path), 1 if slow else args.repeats)
                except Exception as exc:  # the old reader refuses what it cannot read
                    print(f"  {name:<34} refused: {str(exc)[:70]}")
                    continue
                if ours is None:
                    ours = (s, got)
                assert np.allclose(got, ours[1], rtol=1e-5), name
                print(f"  {name:<34} {s * 1000:8.1f} ms   {s / ours[0]:5.2f}x dotshell's")


if __name__ == "__main__":
    main()
