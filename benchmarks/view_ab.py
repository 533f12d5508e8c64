"""Decode + triangulate of the bench view by two source trees, interleaved in one session, each
beside the plain numpy integer decoder of the same frames (:mod:`numpy_gray`) timed in the same
process: the before/after measure of a change to the decoder or the solves (issue 32).

The bench view (full resolution unless ``--quick``) is rendered once; then each round runs
both trees, in alternating order, each in a fresh process that imports only that tree's
dotshell and plugins, loads their compiled passes (one untimed view), and times ``--repeats``
views of ``reconstruct_view`` alternated with the numpy decoder: wall seconds of decode and
triangulate from ``reconstruct_view``'s own timings, CPU seconds of the process (every thread)
for both sides, and the 1-minute load average. At the end: each tree's medians over all its
views and the ratio to the numpy decoder of its own runs, and whether the two trees' points,
pixels and decoded maps are bit-identical. Nothing here asserts a speed.

Run: ``.venv/bin/python benchmarks/view_ab.py --before DIR --after DIR`` where DIR is a
checkout of each tree (``git worktree add`` or ``git archive REV | tar -x -C DIR``);
``--threads 1`` times the passes on one thread.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

SIDES = ("decode", "triangulate", "total", "cpu", "numpy", "numpy_cpu")


def render(work: Path, quick: bool) -> None:
    """The bench view's frames and what decodes them, saved in ``work`` (this tree renders)."""
    from bench_profile import load_bench_profile
    from run import render_view

    from dotshell.plugins import get_plugin_manager
    from dotshell.runtime.process import configure_process

    configure_process()
    pm = get_plugin_manager()
    profile = load_bench_profile(pm, quick)
    view = render_view(profile, pm)
    np.save(work / "frames.npy", view.frames)
    coding = profile.role("coding")
    (work / "view.pkl").write_bytes(pickle.dumps({
        "names": view.names, "calib": view.calib, "angle": view.angle_deg,
        "processing": profile.data["processing"], "backend": coding["backend"],
        "settings": coding["settings"], "projector": view.projector_size}))


def child(tree: Path, work: Path, repeats: int, threads: int, out: Path) -> dict[str, Any]:
    """Time ``tree``'s ``reconstruct_view`` and the numpy decoder, alternated (this process
    imports only ``tree``'s code)."""
    os.environ["DOTSHELL_THREADS"] = str(threads)
    sys.path[:0] = [str(tree), str(tree / "plugins"), str(tree / "benchmarks")]
    from dotshell.runtime.process import configure_process

    configure_process()
    import numpy_gray
    from dotshell.pipeline.reconstruct import reconstruct_view
    from dotshell.plugins import get_plugin_manager
    from dotshell_codings.robust import full_scale

    frames = np.load(work / "frames.npy")
    v = pickle.loads((work / "view.pkl").read_bytes())
    coding = get_plugin_manager().create("coding", v["backend"], v["settings"], None, None)
    shadow_dn = coding.shadow_threshold * full_scale(frames[v["names"].index("white")],
                                                     coding.bit_depth)

    def ours() -> Any:
        return reconstruct_view(0, v["angle"], frames, coding, v["calib"], v["processing"])

    vc = ours()  # untimed: loads (or compiles) the passes
    runs: dict[str, list[float]] = {k: [] for k in SIDES}
    for r in range(repeats):
        for side in (("ours", "numpy") if r % 2 == 0 else ("numpy", "ours")):
            c0, t0 = time.process_time(), time.perf_counter()
            if side == "ours":
                vc = ours()
                runs["cpu"].append(time.process_time() - c0)
                runs["decode"].append(vc.seconds["decode"])
                runs["triangulate"].append(vc.seconds["triangulate"])
                runs["total"].append(vc.seconds["decode"] + vc.seconds["triangulate"])
            else:
                numpy_gray.decode(frames, v["names"], v["projector"], shadow_dn)
                runs["numpy"].append(time.perf_counter() - t0)
                runs["numpy_cpu"].append(time.process_time() - c0)
    corr = vc.correspondence
    np.savez(out, points=vc.points, pixels=vc.pixels, column=corr.column, row=corr.row,
             valid=corr.valid)
    return {"runs": runs, "load": os.getloadavg()[0], "points": int(len(vc.points))}


def compare_outputs(a: Path, b: Path) -> list[str]:
    """Per array: bit-identical, or how far apart."""
    lines = []
    with np.load(a) as x, np.load(b) as y:
        for k in x.files:
            p, q = x[k], y[k]
            if p.shape != q.shape:
                lines.append(f"{k}: shapes differ {p.shape} vs {q.shape}")
            elif np.array_equal(p, q, equal_nan=p.dtype.kind == "f"):
                lines.append(f"{k} {p.shape}: bit-identical")
            else:
                d = np.abs(p.astype(np.float64) - q.astype(np.float64))
                lines.append(f"{k} {p.shape}: {int(np.count_nonzero(d))} values differ, "
                             f"at most {np.nanmax(d):.3g}")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--before", type=Path, help="checkout of the tree before (required)")
    ap.add_argument("--after", type=Path, help="checkout of the tree after (required)")
    ap.add_argument("--rounds", type=int, default=3, help="processes per tree, alternated")
    ap.add_argument("--repeats", type=int, default=7, help="timed views per process")
    ap.add_argument("--threads", type=int, default=2, help="threads of the compiled passes")
    ap.add_argument("--quick", action="store_true", help="the 320x256 bench view")
    ap.add_argument("--child", nargs=4, metavar=("TREE", "WORK", "OUT", "JSON"),
                    help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        tree, work, out, result = (Path(p) for p in args.child)
        Path(result).write_text(json.dumps(child(tree, work, args.repeats, args.threads, out)))
        return
    if args.before is None or args.after is None:
        ap.error("give both --before DIR and --after DIR")
    trees = {"before": args.before.resolve(), "after": args.after.resolve()}
    with tempfile.TemporaryDirectory(prefix="dotshell-view-ab-") as tmp:
        work = Path(tmp)
        render(work, args.quick)
        runs: dict[str, dict[str, list[float]]] = {t: {k: [] for k in SIDES} for t in trees}
        loads = []
        for rnd in range(args.rounds):
            for name in (("before", "after") if rnd % 2 == 0 else ("after", "before")):
                result = work / f"{name}.json"
                cmd = [sys.executable, __file__, "--repeats", str(args.repeats), "--threads",
                       str(args.threads), "--child",
                       str(trees[name]), str(work), str(work / f"{name}.npz"), str(result)]
                env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
                subprocess.run(cmd, check=True, env=env)
                got = json.loads(result.read_text())
                for k in SIDES:
                    runs[name][k] += got["runs"][k]
                loads.append(got["load"])
                print(f"round {rnd + 1} {name:6s} load {got['load']:.1f}: total "
                      f"{statistics.median(got['runs']['total']) * 1e3:.1f} ms, numpy "
                      f"{statistics.median(got['runs']['numpy']) * 1e3:.1f} ms", flush=True)
        print(f"\n== decode + triangulate of the bench view, {args.threads} thread(s), "
              f"{args.rounds} x {args.repeats} views a tree, ms (median / min); load "
              f"{min(loads):.1f}-{max(loads):.1f} ==")
        print(f"  {'':8s}" + "".join(f"{k:>16s}" for k in SIDES) + f"{'ratio':>8s}")
        for name, r in runs.items():
            med = {k: statistics.median(v) * 1e3 for k, v in r.items()}
            print(f"  {name:8s}" + "".join(f"{med[k]:8.1f} /{min(r[k]) * 1e3:6.1f}"
                                           for k in SIDES)
                  + f"{med['total'] / med['numpy']:8.2f}")
        print("  (cpu: the process's CPU seconds over the view, every thread; ratio: total / "
              "numpy, medians)")
        print("\n== the trees' outputs of the last view ==")
        for line in compare_outputs(work / "before.npz", work / "after.npz"):
            print("  " + line)


if __name__ == "__main__":
    main()
