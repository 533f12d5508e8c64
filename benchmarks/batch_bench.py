"""Section 7 of ``make bench``: a study re-processed serially vs on a 2-worker local Dask cluster.

The study is ``RUNS`` copies of one full-resolution scan (frames hard-linked, everything else
copied, so each copy is a run of its own). Serially, one process calls
:func:`dotshell.pipeline.commands.reconstruct_run` on each copy — the best a single process does,
no start-up per run. In parallel, ``dotshell batch reconstruct`` runs on a ``LocalCluster`` of
2 worker processes (1 thread each) over other copies. Both make the same products.

From the batch's measured tasks a scaling model to N workers is derived: work W (task seconds
summed), the critical path D (per run: its slowest view + its tail, the longest run's), the
bounds max(W/N, D) ≤ T(N) ≤ W/N + D (Brent), and the file bandwidth a shared file system must
deliver at N workers (bytes read by the tasks / T(N)).

Run as ``python batch_bench.py serial RESULT_JSON RUN ...`` it is the serial child process.
"""

from __future__ import annotations

import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

BENCH_DIR = Path(__file__).resolve().parent
RUNS, QUICK_RUNS = 12, 4
WORKERS = 2
MODEL_WORKERS = (1, 2, 4, 8, 16, 32, 64, 128)


def make_study(source: Path, dest: Path, n: int) -> list[Path]:
    """``n`` runs copied from ``source``: frames hard-linked (read-only captures), the rest
    copied; each copy keeps only the capture and the published generation."""
    runs = []
    for i in range(n):
        run = dest / f"{i + 1:02d}_{source.name}"
        run.mkdir(parents=True)
        for item in source.iterdir():
            if item.name == "frames":
                subprocess.run(["cp", "-al", str(item), str(run / "frames")], check=True)
            elif item.name != ".lock":
                subprocess.run(["cp", "-a", str(item), str(run / item.name)], check=True)
        runs.append(run)
    return runs


def run_serial(runs: list[Path], work: Path) -> dict[str, Any]:
    """The serial child (a fresh process, like a lab's loop over `dotshell reconstruct`)."""
    result = work / "serial.json"
    t0 = time.perf_counter()
    subprocess.run([sys.executable, str(BENCH_DIR / "batch_bench.py"), "serial", str(result),
                    *map(str, runs)], check=True)
    out = json.loads(result.read_text())
    out["process_wall_s"] = time.perf_counter() - t0
    return out


def warm_up() -> float:
    """Load the plugins and the modules a run's steps import on first use (rendering); the
    serial process and every worker do it before the clock starts. Returns seconds."""
    t0 = time.perf_counter()
    import pyvista  # noqa: F401  (the previews' renderer)

    import dotshell.pipeline.validate  # noqa: F401
    import dotshell.render.previews  # noqa: F401
    from dotshell.plugins import get_plugin_manager

    get_plugin_manager()
    return time.perf_counter() - t0


def serial_child(result: str, runs: list[str]) -> None:
    from dotshell.pipeline.commands import reconstruct_run
    from dotshell.plugins import get_plugin_manager
    from dotshell.runtime.process import configure_process

    configure_process()  # as the dotshell command runs

    start_s = warm_up()
    pm = get_plugin_manager()
    per_run = []
    for run in runs:
        t = time.perf_counter()
        r = reconstruct_run(run, pm)
        per_run.append({"run": Path(run).name, "wall_s": time.perf_counter() - t,
                        "status": r.status, "timings_s": r.report.get("timings_s", {})})
    Path(result).write_text(json.dumps({
        "wall_s": sum(r["wall_s"] for r in per_run), "warm_up_s": start_s,
        "runs": per_run, "peak_rss_mib": resource.getrusage(
            resource.RUSAGE_SELF).ru_maxrss / 1024.0}))


def run_parallel(runs: list[Path]) -> tuple[dict[str, Any], list[Any]]:
    """``dotshell batch reconstruct`` on a fresh local cluster of ``WORKERS`` processes."""
    from dotshell.pipeline.batch import StudyBatch, dask_client
    from dotshell.plugins import get_plugin_manager

    pm = get_plugin_manager()
    t0 = time.perf_counter()
    with dask_client(None, WORKERS) as (client, cluster):
        client.run(warm_up)
        start_s = time.perf_counter() - t0
        t1 = time.perf_counter()
        outcomes = StudyBatch("reconstruct", runs, pm).run(client, cluster)
        wall_s = time.perf_counter() - t1
        rss = client.run(lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)
    return {"cluster_start_s": start_s, "wall_s": wall_s,
            "statuses": sorted({o.status for o in outcomes}),
            "worker_peak_rss_mib": max(rss.values())}, outcomes


def _median(values: list[float]) -> float | None:
    return statistics.median(values) if values else None


def scaling_model(outcomes: list[Any], measured_wall_s: float) -> dict[str, Any]:
    """Task count, work, critical path, bytes per task and T(N) bounds (see the module
    docstring); ``overhead_s`` is the measured 2-worker wall minus W/2 (scheduling, the
    client's planning and publication, idle workers at the study's end)."""
    tasks = [t for o in outcomes for t in o.tasks]
    by_kind: dict[str, list[Any]] = {}
    for t in tasks:
        by_kind.setdefault(t.kind, []).append(t)
    work = sum(t.seconds for t in tasks)
    paths = []
    for o in outcomes:
        views = [t.seconds for t in o.tasks if t.kind == "view"]
        paths.append(sum(t.seconds for t in o.tasks if t.kind != "view") + max(views, default=0))
    span = max(paths, default=0.0)
    total_bytes = sum(t.read_bytes or 0 for t in tasks)
    model = []
    for n in MODEL_WORKERS:
        lower = max(work / n, span)
        model.append({"workers": n, "lower_s": lower, "brent_s": work / n + span,
                      "read_mb_per_s": total_bytes / lower / 1e6 if lower else None})
    return {"tasks": len(tasks), "runs": len(outcomes),
            "per_kind": {k: {"count": len(v), "median_s": _median([t.seconds for t in v]),
                             "max_s": max(t.seconds for t in v),
                             "median_read_mb": _median([(t.read_bytes or 0) / 1e6 for t in v])}
                         for k, v in sorted(by_kind.items())},
            "work_s": work, "critical_path_s": span, "read_mb": total_bytes / 1e6,
            "max_parallelism": work / span if span else None,
            "overhead_s": measured_wall_s - work / WORKERS, "model": model}


def serial_model(serial: dict[str, Any], views: int) -> dict[str, Any]:
    """The same bounds from the serial process's times (a second estimate when other work on
    the machine slowed the batch's tasks): W = the serial wall, D = the slowest run's mean view
    (its ``reconstruct`` / views) plus the rest of its time (an underestimate: a run's slowest
    view is above its mean)."""
    work = sum(r["wall_s"] for r in serial["runs"])
    span = max(r["timings_s"].get("reconstruct", 0.0) / views
               + r["wall_s"] - r["timings_s"].get("reconstruct", 0.0) for r in serial["runs"])
    return {"work_s": work, "critical_path_s": span,
            "model": [{"workers": n, "lower_s": max(work / n, span), "brent_s": work / n + span}
                      for n in MODEL_WORKERS]}


def bench_batch(source: Path, work: Path, quick: bool) -> dict[str, Any]:
    """Section 4's figures (see the module docstring)."""
    n = QUICK_RUNS if quick else RUNS
    serial_runs = make_study(source, work / "study-serial", n)
    batch_runs = make_study(source, work / "study-batch", n)
    load0 = os.getloadavg()[0]
    serial = run_serial(serial_runs, work)
    load1 = os.getloadavg()[0]
    parallel, outcomes = run_parallel(batch_runs)
    load2 = os.getloadavg()[0]
    same = all((a / "cloud.ply").read_bytes() == (b / "cloud.ply").read_bytes()
               for a, b in zip(serial_runs, batch_runs))
    views = len(json.loads((source / "manifest.json").read_text())["views"])
    return {"runs": n, "views_per_run": views, "copies_of_one_run": source.name,
            "serial_model": serial_model(serial, views),
            "serial": serial, "batch": parallel, "clouds_identical": same,
            "loadavg_1min": {"serial_start": load0, "serial_end": load1, "batch_end": load2},
            "ratio_serial_over_batch": serial["wall_s"] / parallel["wall_s"],
            "model": scaling_model(outcomes, parallel["wall_s"])}


def print_batch(b: dict[str, Any]) -> None:
    s, p, m = b["serial"], b["batch"], b["model"]
    print(f"\n== 7. study of {b['runs']} runs x {b['views_per_run']} views: `reconstruct` "
          f"serially vs `dotshell batch reconstruct` on {WORKERS} local workers ==")
    print(f"  the runs are copies of one scan (rendered once; frames hard-linked, the rest "
          f"copied): {b.get('copies_of_one_run', '?')}")
    print(f"  serial, one process       {s['wall_s']:8.1f} s  ({s['wall_s'] / b['runs']:.1f} s "
          f"per run; start-up {s['warm_up_s']:.1f} s before; peak RSS "
          f"{s['peak_rss_mib']:.0f} MiB)")
    print(f"  batch, {WORKERS} workers          {p['wall_s']:8.1f} s  (cluster start-up "
          f"{p['cluster_start_s']:.1f} s before; worker peak RSS "
          f"{p['worker_peak_rss_mib']:.0f} MiB; runs {', '.join(p['statuses'])})")
    print(f"  ratio serial / batch      {b['ratio_serial_over_batch']:8.2f}x   clouds "
          f"byte-identical: {b['clouds_identical']}")
    load = b.get("loadavg_1min", {})
    if load:
        print(f"  1-min load average: serial {load['serial_start']:.1f} -> {load['serial_end']:.1f}, "
              f"batch -> {load['batch_end']:.1f} (other work on the 2 cores slows both sides)")
    print(f"  the tasks' time summed / the serial wall = {m['work_s'] / s['wall_s']:.2f} (1 when "
          "the workers run the same work as fast as the serial process)")
    kinds = ", ".join(f"{k} {v['count']}" for k, v in m["per_kind"].items())
    print(f"  tasks {m['tasks']} ({kinds}); work W = {m['work_s']:.1f} s of task time; critical path D = "
          f"{m['critical_path_s']:.1f} s; W/D = {m['max_parallelism']:.0f} workers at most")
    for k, v in m["per_kind"].items():
        print(f"    {k:5s} median {v['median_s']:6.2f} s, max {v['max_s']:6.2f} s, "
              f"reads {v['median_read_mb']:6.1f} MB (median)")
    print(f"  overhead at {WORKERS} workers: measured wall - W/{WORKERS} = {m['overhead_s']:.1f} s")
    sm = b.get("serial_model")
    if sm:
        print(f"  from the serial times: W = {sm['work_s']:.1f} s, D = "
              f"{sm['critical_path_s']:.1f} s (mean view + tail; an underestimate)")
    print("  model  N workers   max(W/N, D)   W/N + D   file reads needed"
          + ("   serial times: max(W/N, D)   W/N + D" if sm else ""))
    for i, r in enumerate(m["model"]):
        line = (f"         {r['workers']:9d} {r['lower_s']:11.1f} s {r['brent_s']:8.1f} s "
                f"{r['read_mb_per_s']:10.0f} MB/s")
        if sm:
            q = sm["model"][i]
            line += f"   {q['lower_s']:21.1f} s {q['brent_s']:8.1f} s"
        print(line)


def study_alone(quick: bool) -> None:
    """This section alone (``python benchmarks/batch_bench.py study [--quick]``): one scan with
    the bench profile in its own process, then the study; figures printed and written to
    ``bench-results/batch[-quick].json``."""
    import tempfile

    from bench_profile import RESULTS, run_child

    with tempfile.TemporaryDirectory(prefix="dotshell-batch-bench-") as tmp:
        work = Path(tmp)
        t0 = time.perf_counter()
        scanned = run_child("scan", work / "runs", quick, work)
        print(f"rendered and scanned the study's one run in {time.perf_counter() - t0:.0f} s "
              f"(status {scanned['status']})")
        figures = bench_batch(Path(scanned["run_dir"]), work, quick)
    print_batch(figures)
    out = RESULTS.with_name("batch-quick.json" if quick else "batch.json")
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(figures, indent=2, default=str))
    print(f"figures written to {out}")


if __name__ == "__main__" and len(sys.argv) > 2 and sys.argv[1] == "serial":
    serial_child(sys.argv[2], sys.argv[3:])
elif __name__ == "__main__" and len(sys.argv) > 1 and sys.argv[1] == "study":
    study_alone("--quick" in sys.argv[2:])
