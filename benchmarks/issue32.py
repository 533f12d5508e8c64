"""``make bench``'s last section: every row of issue 32's table, the figure of this run beside
the figure the issue measured (main 04737f4, 2 cores, shared) and its bound.

The rows come from the sections before (decode + triangulate and the numpy integer decoder of
the same frames, interleaved in section 2, with the CPU of each; the demo scan and
``reconstruct`` of its run, each in a process of its own) and from two measured here:
``dotshell mesh`` of the demo run in a process of its own (wall, CPU, peak RSS), and
``dotshell --version`` / ``dotshell plugins`` as fresh processes (best of 5, wall and CPU).
CPU seconds are printed beside wall seconds: on a shared machine the wall time of a step
follows the load (printed with every row).
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import time
from typing import Any

#: issue 32's "now" column (main 04737f4) and its bounds
BEFORE = {
    "decode_triangulate": "117 ms vs 28 ms (ratio 4.2)",
    "reconstruct": "17.6 s wall (load 1.2)",
    "mesh": "15.0 s, 1.2 GB peak RSS",
    "last_frame_to_cloud": "not reported",
    "scan": "2 min 42 s (6 min 19 s loaded)",
    "cli": "0.61 s / 0.21 s",
}
BOUND = {
    "decode_triangulate": "<= 30 ms, ratio <= 1.1",
    "reconstruct": "<= 5 s wall at load < 2",
    "mesh": "<= 4 s, <= 600 MB",
    "last_frame_to_cloud": "<= 2 s, printed",
    "scan": "<= 60 s wall, quiet host",
    "cli": "<= 0.3 s / <= 0.15 s",
}


def _child_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def time_command(args: list[str], repeats: int = 5) -> dict[str, float]:
    """Best wall and CPU seconds of ``python -m ARGS`` run ``repeats`` times (fresh processes,
    stdout discarded)."""
    walls, cpus = [], []
    for _ in range(repeats):
        c0, t0 = _child_cpu(), time.perf_counter()
        subprocess.run([sys.executable, "-m", *args], stdout=subprocess.DEVNULL, check=True)
        walls.append(time.perf_counter() - t0)
        cpus.append(_child_cpu() - c0)
    return {"wall_min": min(walls), "cpu_min": min(cpus), "load": os.getloadavg()[0]}


def measure_cli() -> dict[str, Any]:
    """``dotshell plugins`` and ``dotshell --version`` as the console script runs them."""
    return {"plugins": time_command(["dotshell.cli.entry", "plugins"]),
            "version": time_command(["dotshell.cli.entry", "--version"])}


def _rows(results: dict[str, Any]) -> list[tuple[str, str]]:
    """(key, this run's figure) for each row it has figures for."""
    rows = []
    rv, dec = results.get("reconstruct_view"), results.get("decoders")
    if rv and dec:
        ours = rv["total_cores"]["median"] * 1e3
        # the numpy decoder interleaved with reconstruct_view in section 2 (older results:
        # section 3's, timed beside the decoders)
        numpy_ms = (rv["numpy"] if "numpy" in rv else dec["numpy_integer"])["median"] * 1e3
        cpu = (f"; CPU {rv['cpu_cores']['median'] * 1e3:.0f} ms vs "
               f"{rv['cpu_numpy']['median'] * 1e3:.0f} ms" if "cpu_cores" in rv else "")
        rows.append(("decode_triangulate", f"{ours:.1f} ms vs {numpy_ms:.1f} ms (ratio "
                     f"{ours / numpy_ms:.2f}){cpu}; OpenCV getProjPixel "
                     f"{dec['opencv_lit_raster']['median'] * 1e3:.0f} ms"))
    scan = results.get("scan")
    if scan:
        rows.append(("scan", f"{scan['wall_s']:.1f} s wall, {scan['cpu_s']:.1f} s CPU "
                     f"(load {scan.get('load', float('nan')):.1f})"))
        t = scan["report"].get("timings_s", {})
        if "last_frame_to_cloud" in t:
            rows.append(("last_frame_to_cloud", f"{t['last_frame_to_cloud']:.2f} s"))
    rec = results.get("reconstruct_run")
    if rec:
        t = rec["report"].get("timings_s", {})
        rows.append(("reconstruct", f"{rec['wall_s']:.1f} s wall, {rec['cpu_s']:.1f} s CPU "
                     f"(load {rec.get('load', float('nan')):.1f}); merge {t.get('merge', 0):.1f}"
                     f", validate {t.get('validate', 0):.1f}, previews "
                     f"{t.get('previews', 0):.1f} s"))
    mesh = results.get("mesh_run")
    if mesh:
        rows.append(("mesh", f"{mesh['wall_s']:.1f} s wall, {mesh['cpu_s']:.1f} s CPU, "
                     f"{mesh['peak_rss_mib']:.0f} MiB peak (load "
                     f"{mesh.get('load', float('nan')):.1f})"))
    cli = results.get("cli")
    if cli:
        p, v = cli["plugins"], cli["version"]
        rows.append(("cli", f"{p['wall_min']:.2f} s / {v['wall_min']:.2f} s wall; CPU "
                     f"{p['cpu_min']:.2f} / {v['cpu_min']:.2f} s (load {v['load']:.1f})"))
    return rows


def print_table(results: dict[str, Any]) -> None:
    """Issue 32's table: the issue's figure, this run's, the bound."""
    print("\n== issue 32's table: before (main 04737f4) | this run | bound ==")
    for key, now in _rows(results):
        print(f"  {key:20s} {BEFORE[key]:34s} | {now} | {BOUND[key]}")
