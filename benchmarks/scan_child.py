"""Run one end-to-end demo scan, or re-process a run, in its own process and write its figures
as JSON — so that the peak resident memory belongs to that work alone.

Usage (run by ``run.py``)::

    python benchmarks/scan_child.py scan OUT_DIR RESULT_JSON [--quick]
    python benchmarks/scan_child.py reconstruct RUN_DIR RESULT_JSON
    python benchmarks/scan_child.py mesh RUN_DIR RESULT_JSON

BLAS runs on one thread and the heap is set up as in the ``dotshell`` command
(:func:`dotshell.runtime.process.configure_process`).
"""

from __future__ import annotations

import json
import resource
import sys
import time
from pathlib import Path

from bench_profile import load_bench_profile
from dotshell.runtime.process import configure_process
from dotshell.plugins import get_plugin_manager
from dotshell.pipeline.commands import reconstruct_run
from dotshell.pipeline.scan import scan


def own_peak_kib() -> int:
    """This process's own peak resident size (KiB): VmHWM of /proc/self/status. Not
    ``getrusage(RUSAGE_SELF).ru_maxrss``, which on Linux also holds the peak of the process
    that started this one (subprocess vforks, and exec keeps the parent's high-water mark):
    the bench's own ~0.7 GB was reported as the peak of ``reconstruct`` and ``mesh``."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1])
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # not Linux: the best there is


def peak_rss_mib() -> float:
    """Peak resident set size (MiB) of this process or any child it waited for (the mesh
    process: at least this process's size when it was started, see :func:`own_peak_kib`)."""
    return max(own_peak_kib(), resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss) / 1024.0


def cpu_s() -> float:
    """CPU seconds (user + system) of this process so far, every thread, and of the children
    it waited for (the mesh step's process)."""
    return sum(r.ru_utime + r.ru_stime for r in (resource.getrusage(resource.RUSAGE_SELF),
                                                 resource.getrusage(resource.RUSAGE_CHILDREN)))


def main(mode: str, path: str, result_path: str, quick: bool) -> None:
    configure_process()
    pm = get_plugin_manager()
    profile = load_bench_profile(pm, quick)
    t0, c0 = time.perf_counter(), cpu_s()
    if mode == "scan":
        result = scan(profile, pm, Path(path))
    elif mode == "mesh":
        from dotshell.pipeline.commands import mesh_run

        result = mesh_run(path, pm)
    else:
        result = reconstruct_run(path, pm)
    wall, cpu = time.perf_counter() - t0, cpu_s() - c0
    cam = profile.role("camera")["settings"]
    out = {"status": getattr(result, "status", result.report.get("status")), "wall_s": wall, "cpu_s": cpu, "peak_rss_mib": peak_rss_mib(),
           "run_dir": str(result.run_dir), "views": len(profile.angles_deg()),
           "camera": [cam["width"], cam["height"]], "report": result.report}
    Path(result_path).write_text(json.dumps(out, default=str))


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], sys.argv[3], "--quick" in sys.argv[4:])
