"""Where the memory of the agar scan goes (issue 33): ``dotshell scan sim-agar-cylinder`` at full
resolution in a child process, with the resident size (VmRSS, VmHWM of /proc/self/status) and,
with ``--trace``, the largest tracemalloc holders printed at every view boundary.

Usage::

    python benchmarks/agar_memory.py [--views 3] [--trace] [--mesh] [--out DIR] [--before REF]
                                     [--malloc mmap=BYTES,trim=BYTES,arenas=N] [--cold]

``--views N`` scans N views (transillumination at view 0 only, unless N = 12); ``--mesh`` keeps
the profile's mesh and normalization after the scan (they run in a child process of their own).
``--before REF`` measures the dotshell of git revision REF (``git archive``, e.g. ``main``) in
the same run, before this tree: one child process per side, the figures side by side.
``--cold`` gives each side an empty numba cache (``NUMBA_CACHE_DIR``): the first scan after
an install, which compiles every kernel; each side prints how many kernels its scan process
compiled itself (the rest came from the cache, or were compiled in the process
:mod:`dotshell.pipeline.kernel_warmup` starts). ``--malloc`` sets glibc's malloc parameters in place of the command's own
(:mod:`dotshell.runtime.process`) to compare kernel time, page faults and peak RSS; each side
prints its CPU (user, kernel), faults and peak, and the clouds' hashes and accuracy figures.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from io import BytesIO
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def status_mib() -> tuple[float, float]:
    """(VmRSS, VmHWM) of this process, MiB."""
    fields = {}
    for line in Path("/proc/self/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            fields[key] = int(value.split()[0]) / 1024.0
    return fields["VmRSS"], fields["VmHWM"]


class StageSampler:
    """Samples VmRSS every ``period_s`` on a thread and keeps the largest per stage: the
    innermost stage the main thread is in (:meth:`wrap`), ``+ reconstruct`` while the
    reconstruction worker is busy."""

    def __init__(self, period_s: float = 0.05) -> None:
        import threading

        self.stack: list[str] = ["start"]
        self.busy = 0
        self.peaks: dict[str, float] = {}
        self.period_s = period_s
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.done.wait(self.period_s):
            label = self.stack[-1] + (" + reconstruct" if self.busy else "")
            rss = status_mib()[0]
            self.peaks[label] = max(self.peaks.get(label, 0.0), rss)

    def wrap(self, owner: object, name: str, label: str, worker: bool = False) -> None:
        """Label the time spent in ``owner.name`` (a function or method)."""
        import dataclasses
        import functools

        fn = getattr(owner, name)

        @functools.wraps(fn)
        def labelled(*a, **kw):
            if worker:
                self.busy += 1
            else:
                self.stack.append(label)
            try:
                return fn(*a, **kw)
            finally:
                if worker:
                    self.busy -= 1
                else:
                    self.stack.pop()
        if dataclasses.is_dataclass(owner) and not isinstance(owner, type):
            object.__setattr__(owner, name, labelled)  # a Step: a frozen dataclass
        else:
            setattr(owner, name, labelled)


def rusage() -> dict[str, dict[str, float]]:
    """CPU seconds (user, kernel), page faults (minor, major) and peak RSS (MiB) of this
    process and of its waited-for children (the mesh process). The children's peak is
    getrusage's: a child forked from this process counts the parent's pages it shared until
    it ran its own program, so it is at least this process's size at the fork (the mesh
    process's own peak is measured by benchmarks/mesh_bench.py)."""
    import resource

    out = {}
    for who, flag in (("scan", resource.RUSAGE_SELF), ("children", resource.RUSAGE_CHILDREN)):
        ru = resource.getrusage(flag)
        out[who] = {"user_s": ru.ru_utime, "kernel_s": ru.ru_stime, "minor_faults": ru.ru_minflt,
                    "major_faults": ru.ru_majflt, "peak_mib": ru.ru_maxrss / 1024.0}
    return out


def compiled_here() -> dict[str, int]:
    """Kernel signatures this process compiled (not found in numba's cache), by kernel."""
    from numba.core.registry import CPUDispatcher

    found = {}
    for name, module in list(sys.modules.items()):
        for attr, value in list(vars(module).items() if module is not None else ()):
            if issubclass(type(value), CPUDispatcher) and value.__module__ == name:
                misses = sum(value.stats.cache_misses.values())
                if misses:
                    found[f"{name}.{attr}"] = misses
    return found


def outputs(out: Path) -> dict[str, object]:
    """The scan's clouds (sha256 of every PLY, to compare sides byte for byte) and the shape
    validation of its report."""
    import hashlib

    found: dict[str, object] = {}
    for ply in sorted(out.rglob("*.ply")):
        found[str(ply.relative_to(out))] = hashlib.sha256(ply.read_bytes()).hexdigest()[:16]
    for rep in sorted(out.rglob("report.json")):
        validation = json.loads(rep.read_text()).get("validation")
        found[str(rep.relative_to(out))] = validation
    return found


def malloc_settings(spec: str) -> None:
    """glibc malloc settings instead of the command's (``dotshell.runtime.process``), to
    compare them: ``mmap=BYTES,trim=BYTES,arenas=N`` (any of them; ``mmap`` 0 keeps glibc's
    dynamic threshold)."""
    import ctypes
    import ctypes.util

    from dotshell.runtime import process

    params = {"trim": -1, "mmap": -3, "arenas": -8}  # M_TRIM_THRESHOLD, M_MMAP_THRESHOLD, M_ARENA_MAX
    wanted = {k: int(v) for k, v in (item.split("=") for item in spec.split(","))}
    mallopt = ctypes.CDLL(ctypes.util.find_library("c")).mallopt

    def configure() -> None:
        process.limit_blas_threads(1)
        for key, value in wanted.items():
            if not (key == "mmap" and value == 0):
                mallopt(params[key], value)

    process.configure_process = configure


def child(args: argparse.Namespace) -> None:
    """The scan, in this process, with a probe at every view boundary."""
    import tracemalloc

    import dotshell_sim.render as render
    import dotshell_sim.transillum as transillum
    from dotshell.cli.app import main
    from dotshell.pipeline import acquire
    from dotshell.pipeline import scan as scan_module
    from dotshell.pipeline import steps
    from dotshell.pipeline import transillum as pipeline_transillum

    if args.malloc:
        malloc_settings(args.malloc)
    sampler = StageSampler()
    sampler.wrap(acquire.Acquisition, "run_view", "capture fringes")
    sampler.wrap(pipeline_transillum.TransilluminationCapture, "run_view", "trans-illumination")
    sampler.wrap(render.Renderer, "view", "render: new view")
    sampler.wrap(transillum, "laser_view", "laser view")
    sampler.wrap(scan_module, "process", "after the capture")
    sampler.wrap(scan_module, "_transillumination", "flat field")
    sampler.wrap(scan_module.ViewPipeline, "_reconstruct", "", worker=True)
    for step in steps.STEPS:  # the steps after the capture, each on its own
        sampler.wrap(step, "run", f"step {step.name}")
    from dotshell.pipeline import normalize, normalize_outputs
    for owner, name in ((normalize, "unscanned_nodes"), (normalize, "flat_field"),
                        (normalize, "view_surface"), (normalize.Normalization, "_source"),
                        (normalize.TruthAtNodes, "_closest_points"),
                        (normalize_outputs.OutputWriter, "view"),
                        (normalize_outputs, "write_vtu")):  # the normalize step's parts
        sampler.wrap(owner, name, f"normalize: {owner.__name__.split('.')[-1]}.{name}")
    drained: list[float] = []  # seconds the scan waited for reconstructions (trans views)
    if hasattr(scan_module.ViewPipeline, "drain"):
        drain = scan_module.ViewPipeline.drain

        def timed_drain(self) -> None:
            t0 = time.monotonic()
            try:
                drain(self)
            finally:
                drained.append(time.monotonic() - t0)

        scan_module.ViewPipeline.drain = timed_drain  # type: ignore[method-assign]

    if args.trace:
        tracemalloc.start(6)
    records: list[dict] = []
    submit = scan_module.ViewPipeline.submit

    def probe(self, view, angle_deg, frames):  # the moment a view's frames are all captured
        rss, hwm = status_mib()
        rec: dict = {"view": view, "rss_mib": rss, "hwm_mib": hwm, "t_s": time.monotonic()}
        if args.trace:
            snap = tracemalloc.take_snapshot()
            traced = sum(s.size for s in snap.statistics("filename")) / 2**20
            rec["traced_mib"] = traced
            rec["top"] = [(" <- ".join(f"{Path(f.filename).name}:{f.lineno}"
                                       for f in list(s.traceback)[:4]),
                           s.size / 2**20, s.count)
                          for s in snap.statistics("traceback")[:args.top]]
        records.append(rec)
        print(json.dumps(rec), flush=True, file=sys.stderr)
        return submit(self, view, angle_deg, frames)

    scan_module.ViewPipeline.submit = probe  # type: ignore[method-assign]
    sets = [f"scan.views={args.views}"]
    if args.views != 12:
        sets.append("transillumination.views=[0]")
    if not args.mesh:
        sets.append("mesh.after_scan=false")
    argv = ["scan", "sim-agar-cylinder", "--out", args.out, "-q"]
    for s in sets:
        argv += ["--set", s]
    t0 = time.monotonic()
    code = main(argv)
    rss, hwm = status_mib()
    sampler.done.set()
    out = {"exit": code, "wall_s": time.monotonic() - t0, "rss_end_mib": rss, "hwm_mib": hwm,
           "views": records, "stages": sampler.peaks, "rusage": rusage(), "drained_s": drained,
           "outputs": outputs(Path(args.out)), "open3d_loaded": "open3d" in sys.modules,
           "compiled_here": compiled_here(),
           "packages": sorted({m.partition(".")[0] for m in sys.modules
                               if not m.startswith("_")})}
    Path(args.result).write_text(json.dumps(out))


def tree_of(ref: str, where: Path) -> Path:
    """The tree of git revision ``ref`` extracted under ``where``."""
    blob = subprocess.run(["git", "-C", str(ROOT), "archive", ref], check=True,
                          capture_output=True).stdout
    with tarfile.open(fileobj=BytesIO(blob)) as tar:
        tar.extractall(where, filter="data")
    return where


def run_side(label: str, tree: Path, args: argparse.Namespace, tmp: Path) -> dict:
    """One child process scanning with the dotshell of ``tree``."""
    result = tmp / f"{label}.json"
    env = dict(os.environ, PYTHONPATH=f"{tree}:{tree / 'plugins'}", OMP_NUM_THREADS="1",
               OPENBLAS_NUM_THREADS="1")
    if args.cold:
        env["NUMBA_CACHE_DIR"] = str(tmp / f"{label}-numba-cache")
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", "--views", str(args.views),
           "--out", str(tmp / label), "--result", str(result), "--top", str(args.top)]
    cmd += ["--trace"] if args.trace else []
    cmd += ["--mesh"] if args.mesh else []
    cmd += ["--malloc", args.malloc] if args.malloc else []
    subprocess.run(cmd, check=True, env=env, cwd=tree)
    return json.loads(result.read_text())


def report(label: str, res: dict) -> None:
    print(f"\n== {label}: exit {res['exit']}, wall {res['wall_s']:.0f} s, "
          f"peak RSS (VmHWM) {res['hwm_mib']:.0f} MiB, RSS at the end {res['rss_end_mib']:.0f} MiB")
    if "open3d_loaded" in res:
        print(f"  open3d loaded in the scan process: {'yes' if res['open3d_loaded'] else 'no'}")
        print(f"  packages imported: {' '.join(res.get('packages', []))}")
    if "compiled_here" in res:
        here = res["compiled_here"]
        print(f"  kernel signatures compiled in the scan process: {sum(here.values())}"
              + (f" ({', '.join(sorted(here))})" if here else ""))
    if res.get("drained_s"):
        print(f"  waited for the reconstruction before a trans-illumination view: "
              f"{sum(res['drained_s']):.1f} s ({', '.join(f'{s:.1f}' for s in res['drained_s'])})")
    for name, what in res.get("outputs", {}).items():
        print(f"  {name}: {json.dumps(what)[:400]}")
    for who, ru in res.get("rusage", {}).items():
        print(f"  {who}: user {ru['user_s']:.0f} s, kernel {ru['kernel_s']:.0f} s "
              f"({ru['kernel_s'] / max(ru['user_s'] + ru['kernel_s'], 1e-9):.0%}), "
              f"{ru['minor_faults'] / 1e6:.1f} M minor faults, {ru['major_faults']} major, "
              f"peak {ru['peak_mib']:.0f} MiB" + (" (ru_maxrss: at least the scan's size at "
                                                  "the fork)" if who == "children" else ""))
    print("  peak RSS by stage (sampled every 50 ms; main thread's stage, + the reconstruction "
          "worker when busy):")
    for label, mib in sorted(res["stages"].items(), key=lambda kv: -kv[1]):
        print(f"    {mib:7.0f} MiB  {label}")
    t0 = res["views"][0]["t_s"] if res["views"] else 0.0
    for rec in res["views"]:
        traced = f", traced {rec['traced_mib']:.0f} MiB" if "traced_mib" in rec else ""
        print(f"  view {rec['view']} captured at {rec['t_s'] - t0:5.0f} s: RSS "
              f"{rec['rss_mib']:.0f} MiB, HWM {rec['hwm_mib']:.0f} MiB{traced}")
        for where, mib, count in rec.get("top", []):
            print(f"      {mib:7.1f} MiB {count:6d} blocks  {where}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--views", type=int, default=3)
    ap.add_argument("--trace", action="store_true")
    ap.add_argument("--mesh", action="store_true")
    ap.add_argument("--top", type=int, default=12)
    ap.add_argument("--before", default=None)
    ap.add_argument("--malloc", default=None,
                    help="glibc malloc settings instead of the command's: mmap=BYTES,trim=BYTES,"
                         "arenas=N (to compare kernel time, faults and peak RSS)")
    ap.add_argument("--cold", action="store_true",
                    help="each side with an empty numba cache (the first scan after an install)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--result", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args)
        return
    with tempfile.TemporaryDirectory(prefix="agar-mem-", dir=args.out) as tmp_name:
        tmp = Path(tmp_name)
        sides = []
        if args.before:
            sides.append((f"before ({args.before})", tree_of(args.before, tmp / "before-tree")))
        sides.append(("this tree", ROOT))
        results = {label: run_side(label.split()[0], tree, args, tmp) for label, tree in sides}
        for label, res in results.items():
            report(label, res)
        if len(results) == 2:
            (b, a) = results.values()
            print(f"\npeak RSS {b['hwm_mib']:.0f} -> {a['hwm_mib']:.0f} MiB "
                  f"({a['hwm_mib'] / b['hwm_mib']:.2f}x)")


if __name__ == "__main__":
    main()
