"""Where a view's wall time goes between the compiled passes: every call of the decode's and
the triangulation's compiled kernels during ``reconstruct_view`` of the bench view, with its
thread, wall and CPU time, and the gaps in which no kernel ran (Python between the passes,
a core waiting for the other at the end of a pass).

The bench view (full resolution unless ``--quick``) is rendered once; the passes are loaded
by one untimed view, then ``--views`` views are timed at ``--threads`` threads (default: every
core). Printed: per kernel, calls, wall and CPU (``time.thread_time`` of the calling thread) a
view; the wall of the view, the time some kernel ran, and the rest (serial Python); then the
calls of the fastest view in order, with the gap before each (negative: it overlapped the
previous call). Wrapping the kernels costs ~10 µs a call. Nothing here asserts a speed.

Run: ``.venv/bin/python benchmarks/view_timeline.py [--quick] [--threads N] [--views N]``.
"""

from __future__ import annotations

import argparse
import collections
import os
import pickle
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

#: (module, kernels) wrapped: the compiled passes a view calls through module attributes
KERNELS = {
    "dotshell_codings.kernels": ("decode_rows", "difference_extremes", "difference_counts",
                                 "model_levels", "model_residuals", "refine_rows",
                                 "refine_columns", "block_centres"),
    "dotshell.geometry.triangulate": ("_solve_image", "_count_rows", "_select_in_place"),
    "dotshell.pipeline.reconstruct": ("_keep_points", "_gather"),
    "dotshell.pipeline.reversal_pass": ("_count_steps",),
}

Event = tuple[str, int, float, float, float]  # name, thread, start, end, CPU seconds


def wrap_kernels(events: list[Event]) -> None:
    """Replace each kernel of :data:`KERNELS` by a wrapper that records its calls in
    ``events`` (the decode's band joins as ``decode_rows join``)."""
    import importlib

    from dotshell_codings import kernels as decode_kernels

    for module_name, names in KERNELS.items():
        module = importlib.import_module(module_name)
        for name in names:
            if hasattr(module, name):
                setattr(module, name, _recorder(getattr(module, name), name, events,
                                                decode_kernels.JOIN))


def _recorder(fn: Callable[..., Any], name: str, events: list[Event], join: int
              ) -> Callable[..., Any]:
    def call(*args: Any) -> Any:
        c0, t0 = time.thread_time(), time.perf_counter()
        out = fn(*args)
        label = name + (" join" if name == "decode_rows" and args[-4] == join else "")
        events.append((label, threading.get_ident(), t0, time.perf_counter(),
                       time.thread_time() - c0))
        return out

    return call


def busy_time(events: list[Event]) -> float:
    """Seconds in which at least one kernel ran."""
    total, end = 0.0, -np.inf
    for _, _, a, b, _ in sorted(events, key=lambda e: e[2]):
        if a > end:
            total += b - a
            end = b
        elif b > end:
            total += b - end
            end = b
    return total


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="the 320x256 bench view")
    ap.add_argument("--threads", type=int, default=0, help="threads of the passes (0: all)")
    ap.add_argument("--views", type=int, default=9, help="views timed")
    args = ap.parse_args()
    import view_ab

    from dotshell.runtime import parallel
    from dotshell.pipeline.reconstruct import reconstruct_view
    from dotshell.plugins import get_plugin_manager

    with tempfile.TemporaryDirectory(prefix="dotshell-view-timeline-") as tmp:
        view_ab.render(Path(tmp), args.quick)  # also configures the process as the command
        frames = np.load(Path(tmp) / "frames.npy")
        v = pickle.loads((Path(tmp) / "view.pkl").read_bytes())
    coding = get_plugin_manager().create("coding", v["backend"], v["settings"], None, None)
    events: list[Event] = []
    wrap_kernels(events)
    threads = args.threads or parallel.workers()
    per_kernel: dict[str, list[float]] = collections.defaultdict(lambda: [0, 0.0, 0.0])
    views = []
    with parallel.threads(threads):
        reconstruct_view(0, v["angle"], frames, coding, v["calib"], v["processing"])
        for _ in range(args.views):
            events.clear()
            t0 = time.perf_counter()
            reconstruct_view(0, v["angle"], frames, coding, v["calib"], v["processing"])
            wall = time.perf_counter() - t0
            views.append((wall, busy_time(events), list(events), t0))
            for name, _, a, b, cpu in events:
                k = per_kernel[name]
                k[0], k[1], k[2] = k[0] + 1, k[1] + b - a, k[2] + cpu
    n = len(views)
    print(f"reconstruct_view of the bench view, {threads} thread(s), {n} views; 1-min load "
          f"{os.getloadavg()[0]:.1f}\n  {'kernel':24s} {'calls':>6s} {'wall ms':>9s} "
          f"{'CPU ms':>8s}  (a view)")
    for name, (calls, wall, cpu) in sorted(per_kernel.items(), key=lambda kv: -kv[1][2]):
        print(f"  {name:24s} {calls / n:6.1f} {wall / n * 1e3:9.2f} {cpu / n * 1e3:8.2f}")
    walls = np.array([w for w, _, _, _ in views]) * 1e3
    busy = np.array([b for _, b, _, _ in views]) * 1e3
    print(f"  view wall {np.median(walls):.1f} ms (median; min {walls.min():.1f}), a kernel "
          f"running {np.median(busy):.1f} ms, none {np.median(walls - busy):.1f} ms")
    wall, _, evs, t0 = min(views, key=lambda x: x[0])
    print(f"\nthe fastest view ({wall * 1e3:.1f} ms), calls in order (ms):")
    last = t0
    for name, tid, a, b, _ in sorted(evs, key=lambda e: e[2]):
        print(f"  gap {(a - last) * 1e3:6.2f}  {name:22s} {(b - a) * 1e3:6.2f}  thread "
              f"{tid % 10000:04d}")
        last = max(last, b)
    print(f"  gap {(t0 + wall - last) * 1e3:6.2f}  (to the end of reconstruct_view)")


if __name__ == "__main__":
    main()
