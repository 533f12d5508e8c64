"""A view's decode quality (issue 27): what counting the neighbour reversals adds to a view, beside
the view's own decode and triangulation measured in the same process on the same frames.

Two views: the simulated bench view (the metal cylinder, full resolution 1280×1024 unless
``--quick``; ``reconstruct_view``'s own seconds, as a scan records them) and, when the shared
data holds it, the SLStudio skull (real captures, 1688×1352, columns only: decode, triangulate,
quality timed one after the other as ``reconstruct --captures`` runs them). Each is timed
``--repeats`` times on every thread count of ``--threads``; medians in ms.

The peer: the definition before this one (the median of all the steps of each axis by
``np.diff``, as ``dotshell decode`` measured it), kept here, timed on the same maps; both
figures are printed side by side. Nothing here asserts a speed.

Run: ``.venv/bin/python benchmarks/decode_quality.py [--quick] [--repeats 7] [--threads 1 2]``
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

ROOT = Path(__file__).resolve().parents[1]
SKULL = next((p / "shared" / "data" / "slstudio-skull" for p in (ROOT.parent, ROOT.parents[1])
              if (p / "shared" / "data" / "slstudio-skull").is_dir()), None)


def median_slope_reversals(coord: np.ndarray, valid: np.ndarray, step: float = 1.5) -> int:
    """The previous definition (the peer): per axis the median of all steps between adjacent
    valid pixels; the axis of the larger |median| counts the steps of more than ``step``
    against its sign."""
    best, best_slope = 0, -1.0
    for axis in (1, 0):
        d = np.diff(coord, axis=axis)
        both = valid[:, 1:] & valid[:, :-1] if axis == 1 else valid[1:] & valid[:-1]
        steps = d[both]
        if steps.size == 0:
            continue
        slope = float(np.median(steps))
        if abs(slope) > best_slope:
            sign = 1.0 if slope >= 0 else -1.0
            best_slope = abs(slope)
            best = int(np.count_nonzero(sign * steps < -step))
    return best


def median_slope_quality(corr) -> int:
    rev = median_slope_reversals(corr.column, corr.valid)
    if corr.row is not None:
        rev += median_slope_reversals(corr.row, corr.valid)
    return rev


def sim_view(quick: bool) -> Callable[[], tuple[dict[str, float], Any, dict[str, Any]]]:
    """The bench view rendered once; returns a function that reconstructs it and gives
    (seconds by stage, correspondence, quality)."""
    from bench_profile import load_bench_profile
    from run import render_view

    from dotshell.pipeline.reconstruct import reconstruct_view
    from dotshell.plugins import get_plugin_manager

    profile = load_bench_profile(get_plugin_manager(), quick)
    view = render_view(profile, get_plugin_manager())
    processing = profile.data["processing"]

    def once():
        vc = reconstruct_view(0, view.angle_deg, view.frames, view.coding, view.calib,
                              processing)
        return vc.seconds, vc.correspondence, vc.quality

    return once


def skull_view() -> Callable[[], tuple[dict[str, float], Any, dict[str, Any]]]:
    """The SLStudio skull's captures read once; decode, triangulate, quality as
    ``reconstruct --captures`` runs them."""
    from dotshell.geometry.opencv_io import load_any_calibration
    from dotshell.pipeline.decode_quality import view_quality
    from dotshell.pipeline.reconstruct import triangulate_correspondence
    from dotshell.plugins import get_plugin_manager
    from dotshell.run.capture_layouts import load_layout, read_sequence

    layout = load_layout("slstudio-graycode")
    seq = read_sequence(SKULL / "skull_gray", layout, get_plugin_manager())
    calib = load_any_calibration(SKULL / "calibration.xml")
    proc = {"min_ray_angle_deg": 5.0, "row_tolerance_px": 1.5}

    def once():
        t0 = time.perf_counter()
        corr = seq.coding.decode(seq.frames, layout.projector_size)
        t1 = time.perf_counter()
        triangulate_correspondence(corr, calib, proc)
        t2 = time.perf_counter()
        q = view_quality(corr)
        t3 = time.perf_counter()
        return {"decode": t1 - t0, "triangulate": t2 - t1, "quality": t3 - t2}, corr, q

    return once


def measure(name: str, once, repeats: int, thread_counts: list[int]) -> None:
    from dotshell.pipeline.decode_quality import view_quality
    from dotshell.runtime import parallel

    _, corr, q = once()  # untimed: loads (or compiles) the passes
    shape = corr.valid.shape
    print(f"\n{name}: {shape[1]}x{shape[0]} px, decoded {q['decoded_pct']:.2f} %, "
          f"{'column and row maps' if corr.row is not None else 'column map'}")
    for n in thread_counts:
        with parallel.threads(n):
            runs: dict[str, list[float]] = {"decode": [], "triangulate": [], "quality": [],
                                            "median peer": [], "view cpu": [],
                                            "quality cpu": []}
            for _ in range(repeats):
                c0 = time.process_time()
                seconds, corr, q = once()
                c1 = time.process_time()
                view_quality(corr)
                c2 = time.process_time()
                # CPU of every thread: the quality alone (the same work again), and the view
                # without it (decode + triangulate)
                runs["view cpu"].append((c1 - c0) - (c2 - c1))
                runs["quality cpu"].append(c2 - c1)
                for k in ("decode", "triangulate", "quality"):
                    runs[k].append(seconds[k])
                t0 = time.perf_counter()
                old = median_slope_quality(corr)
                runs["median peer"].append(time.perf_counter() - t0)
        ms = {k: 1e3 * statistics.median(v) for k, v in runs.items()}
        view_ms = ms["decode"] + ms["triangulate"]
        print(f"  {n} thread(s), medians of {repeats}, wall: decode {ms['decode']:.1f} ms, "
              f"triangulate {ms['triangulate']:.1f} ms, quality {ms['quality']:.2f} ms "
              f"({100 * ms['quality'] / view_ms:.1f} % of decode + triangulate); the median "
              f"peer {ms['median peer']:.1f} ms ({ms['median peer'] / ms['quality']:.0f}x)")
        print(f"    CPU (every thread): the view {ms['view cpu']:.1f} ms, quality "
              f"{ms['quality cpu']:.2f} ms ({100 * ms['quality cpu'] / ms['view cpu']:.1f} %); "
              f"1-minute load {os.getloadavg()[0]:.1f}")
    print(f"  reversals: {q['reversals']} ({q['reversals_pct']:.3f} % of decoded); the median "
          f"peer's definition: {old}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="the 320x256 bench view")
    ap.add_argument("--repeats", type=int, default=7, help="timed views per thread count")
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2],
                    help="thread counts of the compiled passes")
    ap.add_argument("--no-skull", action="store_true", help="only the simulated view")
    args = ap.parse_args()
    from dotshell.runtime.process import configure_process

    configure_process()
    measure("simulated bench view", sim_view(args.quick), args.repeats, args.threads)
    if SKULL is not None and not args.no_skull:
        measure("SLStudio skull (real captures)", skull_view(), args.repeats, args.threads)


if __name__ == "__main__":
    main()
