"""Compile dotshell's numba kernels into their on-disk cache (``__pycache__/*.nbi, *.nbc`` next to
the sources), once, in the background of the pytest-xdist controller (tests/conftest.py's
``KernelCompile``) while the workers run the test files that call no kernel; a test of any other
file waits for it to end.

Why: a clean clone has no cache, and each worker process compiled every kernel itself, at the
same time as the other (~35 s of CPU each, measured on 2 cores), inside whichever test first
decoded a frame; scans run in subprocesses compiled them again, which also stretched the timings
those tests measure. Compiled here once, every worker and subprocess loads them from the cache.

The kernels are reached through the product's own entry points, so the signatures compiled are
exactly the ones the pipeline asks for, in three groups that share no compiled function and run
at once (each writes its own functions' cache files: dotshell.runtime.numba_cache locks them), each in a
child forked from one process that has imported numba and set its CPU target up (~1.2 s of CPU
that each group's own process paid before), the longest at a higher priority; split so, a cold
cache takes about the longest group's time (~11 s of CPU, 12.5 s of wall time on 2 quiet
cores), not the sum of the three (~20 s):

* ``decode``: one view of the tiny scan decoded (uint16 frames, the one-pass decoder);
* ``triangulate``: ``reconstruct_view`` of the tiny scan's rig on a correspondence laid out as
  the decoder's (the solves, the speckle test, the region of interest, the selection);
* ``fem``: a forward solve on one tetrahedron (the FEM assembly's kernels).

``scan`` (not run by the tests) makes the tiny 1-view scan itself: once the groups have run it
loads every kernel from the cache and compiles nothing (``NUMBA_DEBUG_CACHE=1`` shows it),
which is how the groups are checked against what a scan asks for.

Variants only a few test files need (float32 frames of PDI views, the XOR codes' passes,
columns-only codings) are left to the worker that first needs them: compiled here they would
hold both workers back.

Run: ``python tests/compile_kernels.py [decode|triangulate|fem|scan]`` (those in this process,
one after the other; without argument the three groups in forked children at once, as the tests
run them); prints the seconds.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
import traceback
from collections.abc import Sequence
from contextlib import contextmanager
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

#: longest first (CPU of a cold compile on 2 quiet cores: ~11, ~5 and ~3.5 s)
GROUPS = ("decode", "triangulate", "fem")

#: the groups after the first yield to it: on 2 cores the scheduler then gives the longest
#: group a core of its own and the two shorter ones share the other (two tasks of weight 526
#: against one of 1024), instead of each of the three taking 2/3 of a core (the longest would
#: finish last, after ~3/2 of its CPU time); not more, so that on a machine busy with other
#: work the shorter groups do not become the last to finish
LATER_GROUPS_NICENESS = 3


@contextmanager
def _tiny_scan(tmp_prefix: str = "dotshell-compile-"):
    """(plugin manager, loaded 1-view profile, temporary directory) of the tiny scan the tests
    run, the directory removed at the end."""
    from conftest import small_profile_dict, write_profile
    from dotshell.plugins import PluginManager
    from dotshell.profile.loader import load_profile

    pm = PluginManager()
    pm.load_entry_points()
    raw = small_profile_dict(factor=0.12, views=1)
    raw["camera"]["settings"]["supersample"] = 1
    raw["outputs"] = {"previews": False}
    with tempfile.TemporaryDirectory(prefix=tmp_prefix) as tmp:
        yield pm, load_profile(write_profile(Path(tmp) / "p.toml", raw), pm), Path(tmp)


def compile_decode_kernels() -> None:
    """The decoder's kernels: one view of the tiny scan captured on the simulated rig and
    decoded as ``reconstruct_view`` decodes it."""
    from dotshell.pipeline.steps import make_coding
    from dotshell.rig.assembly import Rig

    with _tiny_scan() as (pm, profile, _), Rig(profile, pm) as rig:
        coding = make_coding(profile, pm)
        rig.stage.move_to(profile.angles_deg()[0])
        frames = []
        for pattern in coding.patterns(rig.projector.resolution):
            rig.projector.show(pattern.image)
            frames.append(rig.camera.capture())
        coding.decode(frames, tuple(rig.projector.resolution))


def compile_triangulate_kernels() -> None:
    """The triangulation's and the reconstruction's kernels: ``reconstruct_view`` of the tiny
    scan's rig on a correspondence laid out as the decoder returns it (its maps on huge pages,
    a band of pixels decoded), without decoding (the decode group compiles that at the same
    time; the two groups share no compiled function)."""
    import numpy as np

    from dotshell.runtime import hugepages
    from dotshell.coding import Correspondence
    from dotshell.pipeline.reconstruct import reconstruct_view
    from dotshell.rig.assembly import Rig

    class Decoded:
        def decode(self, frames, projector_size):
            h, w = frames[0].shape
            coord = hugepages.empty((2, h, w), np.float32)
            valid = hugepages.empty((h, w), bool)
            valid[:] = False
            valid[h // 3:2 * h // 3, w // 3:2 * w // 3] = True
            v, u = np.mgrid[0:h, 0:w]
            coord[0] = u * (projector_size[0] / w)
            coord[1] = v * (projector_size[1] / h)
            return Correspondence(coord[0], coord[1], valid)

    with _tiny_scan() as (pm, profile, _), Rig(profile, pm) as rig:
        calib = rig.calibration()
        w, h = calib.camera.size
        frames = [np.zeros((h, w), np.uint16)] * 2
        reconstruct_view(0, profile.angles_deg()[0], frames, Decoded(), calib,
                         profile.data["processing"])


def compile_scan_kernels() -> None:
    """Every scan kernel through a 1-view scan (loads them from the cache once the groups
    above have compiled them: the check that they compiled what a scan asks for)."""
    from dotshell.pipeline.scan import scan

    with _tiny_scan() as (pm, profile, tmp):
        scan(profile, pm, tmp / "runs")


def compile_fem_kernels() -> None:
    """The FEM assembly's kernels (:mod:`dotshell.fem.kernels`) through ``solve_cw`` on one
    tetrahedron (the forward solve of test_fem, test_sim_transillum and the mesh pipeline)."""
    import numpy as np

    from dotshell.fem.meshes import TetMesh, orient_positive
    from dotshell.fem.forward import solve_cw

    nodes = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)
    mesh = TetMesh(nodes, orient_positive(nodes, np.array([[0, 1, 2, 3]])))
    solve_cw(mesh, [0.0, 0.0, 0.0], 0.01, 1.0, 1.33)


def _prepare_for_forks() -> None:
    """What every group's process needs before it compiles, done once in the parent: numba
    imported and its CPU target set up (a first compile loads the registries of its numpy
    support, scipy's BLAS included: ~1.2 s of CPU that each group's process paid), and the
    modules the tiny scan loads."""
    import numba
    import numpy  # noqa: F401

    import dotshell.plugins  # noqa: F401
    import dotshell.profile.loader  # noqa: F401

    numba.njit("int64(int64)")(lambda x: x + 1)  # not cached: sets the target up, writes nothing


def compile_in_forks(groups: Sequence[str]) -> list[str]:
    """Each group in a child forked from this process after :func:`_prepare_for_forks`, all at
    once (so each child compiles its kernels and little else), the first at a higher priority
    than the others (:data:`LATER_GROUPS_NICENESS`); each child's output is printed after it,
    under its name, with its CPU time. Returns the groups that failed."""
    _prepare_for_forks()
    sys.stdout.flush()
    sys.stderr.flush()
    children = {}
    for i, group in enumerate(groups):
        log = tempfile.TemporaryFile("w+")
        pid = os.fork()
        if pid == 0:  # the child: never returns into the parent's code
            status = 1
            try:
                os.dup2(log.fileno(), 1)
                os.dup2(log.fileno(), 2)
                if i > 0:
                    os.nice(LATER_GROUPS_NICENESS)
                _run(group)
                status = 0
            except BaseException:
                traceback.print_exc()
            finally:
                sys.stdout.flush()
                sys.stderr.flush()
                os._exit(status)
        children[pid] = (group, log)
    failed = []
    for pid, (group, log) in children.items():
        _, status, usage = os.wait4(pid, 0)
        log.seek(0)
        print(f"{group}: {log.read().strip()} "
              f"({usage.ru_utime + usage.ru_stime:.1f} s of CPU)")
        log.close()
        if os.waitstatus_to_exitcode(status) != 0:
            failed.append(group)
    return failed


def _run(group: str) -> None:
    """One group (or ``scan``) in this process (raises if it fails); prints its seconds."""
    t0 = time.perf_counter()
    {"decode": compile_decode_kernels, "triangulate": compile_triangulate_kernels,
     "scan": compile_scan_kernels, "fem": compile_fem_kernels}[group]()
    print(f"kernels compiled or loaded from the cache in {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    for name in sys.argv[1:]:
        _run(name)
    failed = [] if sys.argv[1:] else compile_in_forks(GROUPS)
    if failed:
        print(f"failed: {', '.join(failed)}")
    sys.exit(1 if failed else 0)
