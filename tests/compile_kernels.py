"""Compile dotshell's numba kernels into their on-disk cache (``__pycache__/*.nbi, *.nbc`` next to
the sources), once, before the test workers start (tests/conftest.py runs this in the pytest-xdist
controller).

Why: a clean clone has no cache, and each worker process compiled every kernel itself, at the
same time as the other (~35 s of CPU each, measured on 2 cores), inside whichever test first
decoded a frame; scans run in subprocesses compiled them again, which also stretched the timings
those tests measure. Compiled here once, every worker and subprocess loads them from the cache.

The kernels are reached through the product's own entry points (a tiny scan: uint16 frames
decoded, triangulated, reconstructed; a decode of uint8 and float32 frames, in one pass and
(XOR codes) in passes; a forward solve on
one tetrahedron), so the signatures compiled are exactly the ones the pipeline asks for.

Run: ``python tests/compile_kernels.py`` (prints the seconds it took).
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def compile_kernels() -> None:
    import numpy as np

    from conftest import small_profile_dict, write_profile
    from dotshell.pipeline.scan import scan
    from dotshell.plugins import PluginManager
    from dotshell.profile import load_profile
    from dotshell.settings import validate_settings
    from dotshell_codings import dotshell_codings

    pm = PluginManager()
    pm.load_entry_points()
    raw = small_profile_dict(factor=0.12, views=1)
    raw["camera"]["settings"]["supersample"] = 1
    raw["outputs"] = {"previews": False}
    with tempfile.TemporaryDirectory(prefix="dotshell-compile-") as tmp:
        prof = load_profile(write_profile(Path(tmp) / "p.toml", raw), pm)
        scan(prof, pm, Path(tmp) / "runs")
    (graycode,) = [b for b in dotshell_codings() if b.name == "graycode"]
    coding = graycode.factory(settings=validate_settings(graycode.settings_schema, {}, "compile"),
                              context=None)
    proj = (64, 16)
    images = [p.image for p in coding.patterns(proj)]
    (xor,) = [b for b in dotshell_codings() if b.name == "xor02"]
    xor_coding = xor.factory(settings=validate_settings(xor.settings_schema, {}, "compile"),
                             context=None)
    xor_images = [p.image for p in xor_coding.patterns(proj)]
    for frames, xor_frames in ((images, xor_images),
                               ([im.astype(np.float32) for im in images],
                                [im.astype(np.float32) for im in xor_images])):
        coding.decode(frames, proj)  # the one-pass decoder
        xor_coding.decode(xor_frames, proj)  # the passes (XOR codes, stripes the other way)
    _compile_fem_kernels()


def _compile_fem_kernels() -> None:
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
    compile_kernels()
    print(f"kernels compiled or loaded from the cache in {time.perf_counter() - t0:.1f} s")
