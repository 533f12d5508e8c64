"""Run one end-to-end demo scan in its own process and write its figures as JSON.

Usage: ``python benchmarks/scan_child.py OUT_DIR RESULT_JSON [--quick]``. Run by ``run.py`` as
a subprocess so that the peak resident memory belongs to the scan alone.
"""

from __future__ import annotations

import json
import resource
import sys
import time
from pathlib import Path

from bench_profile import load_bench_profile
from dotshell.plugins import get_plugin_manager
from dotshell.pipeline.scan import scan


def peak_rss_mib() -> float:
    """Peak resident set size (MiB) of this process or any child it waited for (Linux: KiB)."""
    kib = max(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
              resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
    return kib / 1024.0


def main(out_dir: str, result_path: str, quick: bool) -> None:
    pm = get_plugin_manager()
    profile = load_bench_profile(pm, quick)
    t0 = time.perf_counter()
    result = scan(profile, pm, Path(out_dir))
    wall = time.perf_counter() - t0
    cam = profile.role("camera")["settings"]
    out = {"status": result.status, "wall_s": wall, "peak_rss_mib": peak_rss_mib(),
           "views": len(profile.angles_deg()), "camera": [cam["width"], cam["height"]],
           "report": result.report}
    Path(result_path).write_text(json.dumps(out, default=str))


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], "--quick" in sys.argv[3:])
