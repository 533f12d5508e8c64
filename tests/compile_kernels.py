"""Compile dotshell's numba kernels into their on-disk cache (``__pycache__/*.nbi, *.nbc`` next to
the sources), once, before the test workers start (tests/conftest.py runs this in the pytest-xdist
controller).

Why: a clean clone has no cache, and each worker process compiled every kernel itself, at the
same time as the other (~35 s of CPU each, measured on 2 cores), inside whichever test first
decoded a frame; scans run in subprocesses compiled them again, which also stretched the timings
those tests measure. Compiled here once, every worker and subprocess loads them from the cache.

The kernels are reached through the product's own entry points, so the signatures compiled are
exactly the ones the pipeline asks for, in two groups that share no compiled function and run
as two processes at once (numba's cache index of one function must not be written by two
processes):

* ``scan``: a tiny scan (uint16 frames decoded in one pass, triangulated, reconstructed), what
  nearly every test file runs;
* ``fem``: a forward solve on one tetrahedron (the FEM assembly's kernels).

Variants only a few test files need (float32 frames of PDI views, the XOR codes' passes) are
left to the worker that first needs them: compiled here they would hold both workers back.

Run: ``python tests/compile_kernels.py [scan|fem]`` (both without argument; prints the seconds).
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

GROUPS = ("scan", "fem")


def compile_scan_kernels() -> None:
    """The decoder's, triangulation's and reconstruction's kernels through a 1-view scan."""
    from conftest import small_profile_dict, write_profile
    from dotshell.pipeline.scan import scan
    from dotshell.plugins import PluginManager
    from dotshell.profile import load_profile

    pm = PluginManager()
    pm.load_entry_points()
    raw = small_profile_dict(factor=0.12, views=1)
    raw["camera"]["settings"]["supersample"] = 1
    raw["outputs"] = {"previews": False}
    with tempfile.TemporaryDirectory(prefix="dotshell-compile-") as tmp:
        prof = load_profile(write_profile(Path(tmp) / "p.toml", raw), pm)
        scan(prof, pm, Path(tmp) / "runs")


def compile_fem_kernels() -> None:
    """The FEM assembly's kernels (:mod:`dotshell.fem_kernels`) through ``solve_cw`` on one
    tetrahedron (the forward solve of test_fem, test_sim_transillum and the mesh pipeline)."""
    import numpy as np

    from dotshell.fem import TetMesh, orient_positive
    from dotshell.forward import solve_cw

    nodes = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)
    mesh = TetMesh(nodes, orient_positive(nodes, np.array([[0, 1, 2, 3]])))
    solve_cw(mesh, [0.0, 0.0, 0.0], 0.01, 1.0, 1.33)


if __name__ == "__main__":
    t0 = time.perf_counter()
    for group in sys.argv[1:] or GROUPS:
        {"scan": compile_scan_kernels, "fem": compile_fem_kernels}[group]()
    print(f"kernels compiled or loaded from the cache in {time.perf_counter() - t0:.1f} s")
