"""The numba triangle hierarchy (:class:`dotshell.geometry.bvh.TriangleBVH`) against open3d's
``RaycastingScene`` (:class:`dotshell.geometry.raycast.TriangleScene`) on the scan's two
workloads, in the same process: closest points of the camera sub-samples on a FEM boundary (the
simulator's trans-illumination truth: ~2.7 M points a full-resolution agar view) and camera rays
cast at a surface mesh (the normalization's mapping), plus the resident size each adds.

Usage::

    python benchmarks/bvh_bench.py [--points 2700000] [--rays 1310720] [--spacing 1.0]

The mesh is a closed cylinder (the agar's radius 12.92 mm, 30 mm tall) with triangles of
~``--spacing`` mm; each timing is the best of ``--repeat`` calls, after a first call (numba's
cached code loaded, open3d's scene built).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from frame_checks import best_of  # the smallest wall time (s) of a few calls


def rss_mib() -> float:
    """VmRSS of this process, MiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def cylinder(radius: float, height: float, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """A closed triangulated cylinder (axis z, base at z = 0) with edges of ~``spacing`` mm."""
    n_a = max(8, int(round(2 * np.pi * radius / spacing)))
    n_z = max(1, int(round(height / spacing)))
    a = np.arange(n_a) * 2 * np.pi / n_a
    rings = [np.column_stack([radius * np.cos(a + (k % 2) * np.pi / n_a),
                              radius * np.sin(a + (k % 2) * np.pi / n_a),
                              np.full(n_a, k * height / n_z)]) for k in range(n_z + 1)]
    vertices = np.vstack(rings + [[[0, 0, 0]], [[0, 0, height]]])
    tri = []
    for k in range(n_z):
        for i in range(n_a):
            j = (i + 1) % n_a
            p, q, r, s = k * n_a + i, k * n_a + j, (k + 1) * n_a + i, (k + 1) * n_a + j
            tri += [(p, q, s), (p, s, r)] if k % 2 == 0 else [(p, q, r), (q, s, r)]
    bottom, top = len(vertices) - 2, len(vertices) - 1
    for i in range(n_a):
        j = (i + 1) % n_a
        tri += [(bottom, j, i), (top, n_z * n_a + i, n_z * n_a + j)]
    return vertices, np.array(tri, np.int64)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=2_700_000)
    ap.add_argument("--rays", type=int, default=1280 * 1024)
    ap.add_argument("--spacing", type=float, default=1.0)
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args()
    vertices, triangles = cylinder(12.92, 30.0, args.spacing)
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 2 * np.pi, args.points)
    r = 12.92 + rng.normal(0.0, 0.02, args.points)  # the true surface, off the facets
    z = rng.uniform(0.5, 29.5, args.points)
    order = np.lexsort((a, np.floor(z / 0.05)))  # in rows, as a camera image's sub-samples
    points = np.column_stack([r * np.cos(a), r * np.sin(a), z])[order]
    camera = np.array([200.0, 0.0, 15.0])
    side = int(np.sqrt(args.rays))  # a camera's rows of pixels across the cylinder
    yy, zz = np.meshgrid(np.linspace(-16, 16, side), np.linspace(-2, 32, args.rays // side))
    target = np.column_stack([np.zeros(yy.size), yy.ravel(), zz.ravel()])
    dirs = target - camera
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origins = np.broadcast_to(camera, dirs.shape)
    print(f"cylinder: {len(triangles)} triangles; {args.points} points, {len(dirs)} rays")

    import numba  # noqa: F401  (the scan process has numba loaded: not counted for either)

    from dotshell.geometry.bvh import TriangleBVH

    base = rss_mib()
    ours = TriangleBVH(vertices, triangles)
    ours.closest(points[:10])
    ours.cast(origins[:10], dirs[:10])
    ours_mib = rss_mib() - base
    from dotshell.geometry.raycast import TriangleScene

    base = rss_mib()
    theirs = TriangleScene(vertices, triangles)
    theirs.closest(points[:10])
    theirs.cast(origins[:10], dirs[:10])
    theirs_mib = rss_mib() - base
    rows = []
    for what, call in (("closest", lambda s: s.closest(points)),
                       ("cast", lambda s: s.cast(origins, dirs))):
        t_ours = best_of(lambda: call(ours), args.repeat)
        t_theirs = best_of(lambda: call(theirs), args.repeat)
        rows.append((what, t_ours, t_theirs))
    gap = ours.closest(points[:200_000]).distance_mm - theirs.closest(points[:200_000]).distance_mm
    for what, t_ours, t_theirs in rows:
        print(f"{what:8s} bvh {t_ours:6.2f} s   open3d {t_theirs:6.2f} s   ({t_ours / t_theirs:.2f}x)")
    print(f"resident size added (import beside numba + scene + first queries): bvh {ours_mib:.0f} MiB, "
          f"open3d {theirs_mib:.0f} MiB")
    print(f"closest distance, bvh - open3d (200 k points): max {gap.max():+.2e} mm, "
          f"min {gap.min():+.2e} mm")


if __name__ == "__main__":
    main()
