"""Peak memory of the surface mesher on a full-resolution cloud (issue 33: the agar profile's
scan peaked at 2.1-2.6 GB, the mesh step being the largest).

A cloud like the agar cylinder's at full resolution (8.3 M points: 12 views of ~690 k, the
points of a 15 mm radius, 30 mm high cylinder with 0.02 mm noise, each with its view's camera
position) is meshed at 1 mm by the ``open3d-poisson`` surface mesher in a fresh child process,
twice, interleaved: thinning the cloud a chunk of ``THIN_CHUNK`` points at a time (dotshell),
and the whole cloud at once (the peer: dotshell before issue 33, ``THIN_CHUNK`` larger than the
cloud). Each child reports its peak RSS (``resource.getrusage``: ``ru_maxrss``), its peak
before meshing (the cloud and the imports) and the seconds of the ``surface()`` call.

    python benchmarks/mesh_memory_bench.py [--points 8300000] [--repeats 1]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

CHILD = r"""
import json, resource, sys, time
import numpy as np
import dotshell_meshing.surface as surface
from dotshell_meshing.surface import SETTINGS as SCHEMA
from dotshell.settings import validate_settings

n, whole = int(sys.argv[1]), sys.argv[2] == "whole"
rng = np.random.default_rng(1)
views = rng.integers(0, 12, n)
angle = np.deg2rad(views * 30.0 + rng.uniform(-60, 60, n))
r = 15.0 + rng.normal(0, 0.02, n)
points = np.column_stack([r * np.cos(angle), r * np.sin(angle), rng.uniform(0, 30, n)])
order = np.argsort(views, kind="stable")  # a merged cloud lists its points view by view
points = points[order]
cams = np.deg2rad(np.arange(12) * 30.0)
viewpoints = np.column_stack([200 * np.cos(cams), 200 * np.sin(cams), np.full(12, 15.0)])
viewpoints = viewpoints[views[order]]
del angle, r, order
if whole:
    surface.THIN_CHUNK = n + 1
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
mesher = surface.PoissonSurfaceMesher(validate_settings(SCHEMA, {}, "bench"))
t0 = time.perf_counter()
result = mesher.surface(points, viewpoints, 1.0, None)
print(json.dumps({"seconds": time.perf_counter() - t0, "before_mb": before / 1024,
                  "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "vertices": len(result.surface.vertices)}))
"""


def run_child(points: int, mode: str) -> dict:
    proc = subprocess.run([sys.executable, "-c", CHILD, str(points), mode], capture_output=True,
                          text=True, check=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=8_300_000)
    ap.add_argument("--repeats", type=int, default=1)
    args = ap.parse_args()
    results: dict[str, list[dict]] = {"chunked": [], "whole": []}
    for i in range(args.repeats):
        for mode in (("chunked", "whole") if i % 2 == 0 else ("whole", "chunked")):
            results[mode].append(run_child(args.points, mode))
    for mode, runs in results.items():
        peak = min(r["peak_mb"] for r in runs)
        print(f"{mode:8s} peak RSS {peak:7.0f} MB (before meshing {runs[0]['before_mb']:.0f} MB), "
              f"surface() {min(r['seconds'] for r in runs):.1f} s, "
              f"{runs[0]['vertices']} vertices")
    gain = (min(r["peak_mb"] for r in results["whole"])
            - min(r["peak_mb"] for r in results["chunked"]))
    print(f"chunked thinning saves {gain:.0f} MB of peak RSS "
          f"({gain / (min(r['peak_mb'] for r in results['whole'])) * 100:.0f} %)")


if __name__ == "__main__":
    main()
