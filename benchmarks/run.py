"""dotshell benchmarks (``make bench``): speed and memory against peers measured in the same run.

1. Frame I/O of one view: the PNG files runs used to write against the TIFF stack they write now
   (:mod:`frame_io`).
2. ``reconstruct_view`` of one view (simulated reference bench, full resolution by default):
   decode and triangulate (BLAS on one thread, as the ``dotshell`` command runs it), with the
   compiled passes split across every core and on one thread (``DOTSHELL_THREADS``), and the
   plain numpy integer decoder of the same frames (:mod:`numpy_gray`, issue 32's peer),
   interleaved, with the CPU seconds of each.
3. Decoders on the same frames, interleaved (:mod:`decoders`): dotshell's; the decoder before
   issue 16 part 2 (``graycode_before``, frozen), with a bit-for-bit comparison; OpenCV contrib's
   ``GrayCodePattern.getProjPixel`` on every lit pixel in raster order, in its own venv
   (``.venv-bench-contrib``, created on first use; opencv-contrib conflicts with the project's
   opencv-python-headless); a plain numpy integer decoder (:mod:`numpy_gray`).
4. The end-to-end demo scan in a subprocess (wall time by stage, peak memory, accuracy), then
   ``reconstruct`` of that run in another (wall time, peak memory).
5. Acquisition rate of show/settle/capture vs hardware-sequenced on the simulator's time model
   (``acquisition_rate.py``): frames per second, seconds per 42-frame view, their ratio.
6. An idle ``dotshell tui`` attached to its rig server after a 4-view scan: resident memory and
   CPU; peer: a bare Textual app on the same pseudo-terminal (``bench_tui.py``).
7. A study of 12 copies of that scan re-processed serially vs by ``dotshell batch`` on a
   2-worker local Dask cluster, and a model of the scaling to N workers (:mod:`batch_bench`;
   ``--skip-batch`` leaves it out).
8. ``dotshell forward``'s CW solve (Jacobi CG) on the agar cylinder's ~31 k-node volume mesh
   against ``splu`` (COLAMD) of the same system, interleaved (:mod:`forward_bench`; no scan).

Every figure is printed beside the baseline recorded in ``benchmarks/baseline.json`` (the figures
before issue 16, same machine). Results go to ``bench-results/latest.json``
(``latest-quick.json`` with ``--quick``, so a harness check never replaces the full figures).
``--quick`` scales the bench down (camera 320×256, projector 256×192, 2 views) to test the
harness. Nothing here asserts a speed.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

import acquisition_rate
import batch_bench
import decoders
import forward_bench
import frame_io
import issue32
import numpy_gray
from bench_profile import RESULTS, ROOT, load_bench_profile, run_child
from dotshell.runtime import parallel
from dotshell.runtime.process import configure_process
from dotshell.coding import PatternCoding
from dotshell.devices import ExposureControl
from dotshell.geometry.calibration import RigCalibration
from dotshell.pipeline.reconstruct import reconstruct_view
from dotshell.plugins import PluginManager, get_plugin_manager
from dotshell.profile.loader import Profile
from dotshell.rig.assembly import Rig
from dotshell_codings.robust import full_scale

BENCH_DIR = Path(__file__).resolve().parent
CONTRIB_VENV = ROOT / ".venv-bench-contrib"
BASELINE = BENCH_DIR / "baseline.json"


@dataclass
class RenderedView:
    """One view's frames (frames, height, width) as captured, with what decodes them."""

    angle_deg: float
    names: list[str]
    frames: np.ndarray
    coding: PatternCoding
    calib: RigCalibration
    projector_size: tuple[int, int]
    bit_depth: int
    render_s: float


def make_coding(profile: Profile, pm: PluginManager, **overrides: Any) -> PatternCoding:
    c = profile.role("coding")
    return pm.create("coding", c["backend"], {**c["settings"], **overrides}, None,
                     profile.source)


def render_view(profile: Profile, pm: PluginManager) -> RenderedView:
    """Render view 0 with the simulator; ``render_s`` is the simulator time (stage move + show
    + capture, seconds)."""
    coding = make_coding(profile, pm)
    angle = profile.angles_deg()[0]
    with Rig(profile, pm) as rig:
        calib = rig.calibration()
        if isinstance(rig.camera, ExposureControl):
            rig.camera.set_exposure(profile.data["scan"]["exposure_ms"])
        patterns = coding.patterns(rig.projector.resolution)
        t0 = time.perf_counter()
        rig.stage.move_to(angle)
        captured = []
        for p in patterns:
            rig.projector.show(p.image)
            captured.append(rig.camera.capture())
        render_s = time.perf_counter() - t0
        projector_size, bit_depth = tuple(rig.projector.resolution), int(rig.camera.bit_depth)
    return RenderedView(angle, [p.name for p in patterns], np.stack(captured), coding, calib,
                        projector_size, bit_depth, render_s)


# ---- 2. reconstruct_view --------------------------------------------------------------------

def time_reconstruct(view: RenderedView, processing: dict[str, Any], repeats: int
                     ) -> dict[str, Any]:
    """Decode / triangulate seconds of ``reconstruct_view`` (min and median of ``repeats``),
    the compiled passes split across every core and on one thread, and the plain numpy
    integer decoder of the same frames (:mod:`numpy_gray`, issue 32's peer), interleaved in
    turn; with the process's CPU seconds (every thread) of each."""
    cores = parallel.workers()
    shadow_dn = view.coding.shadow_threshold * full_scale(
        view.frames[view.names.index("white")], view.coding.bit_depth)
    # untimed first run: loads the compiled passes from numba's cache (or compiles them)
    reconstruct_view(0, view.angle_deg, view.frames, view.coding, view.calib, processing)
    runs: dict[str, list[dict[str, float]]] = {"cores": [], "one": [], "numpy": []}
    keys = list(runs)
    for r in range(repeats):
        for key in keys[r % len(keys):] + keys[:r % len(keys)]:
            c0, t0 = time.process_time(), time.perf_counter()
            if key == "numpy":
                numpy_gray.decode(view.frames, view.names, view.projector_size, shadow_dn)
                runs[key].append({"decode": time.perf_counter() - t0})
            else:
                with parallel.threads(cores if key == "cores" else 1):
                    vc = reconstruct_view(0, view.angle_deg, view.frames, view.coding,
                                          view.calib, processing)
                runs[key].append(dict(vc.seconds))
            runs[key][-1]["cpu"] = time.process_time() - c0
    out: dict[str, Any] = {"numpy": frame_io.min_median([r["decode"] for r in runs["numpy"]])}
    for key, rs in runs.items():
        out[f"cpu_{key}"] = frame_io.min_median([r["cpu"] for r in rs])
        if key == "numpy":
            continue
        for stage in ("decode", "triangulate"):
            out[f"{stage}_{key}"] = frame_io.min_median([r[stage] for r in rs])
        out[f"total_{key}"] = frame_io.min_median([r["decode"] + r["triangulate"] for r in rs])
    h, w = view.frames[0].shape
    out.update(repeats=repeats, decoded_px=int(vc.correspondence.valid.sum()),
               points=int(len(vc.points)), camera_px=[w, h], frames=len(view.frames),
               render_s=view.render_s, threads=cores)
    return out


def _vs(now_s: float, before_ms: float | None) -> str:
    if not before_ms:
        return ""
    return f"   baseline {before_ms:7.1f} ms ({before_ms / (now_s * 1e3):.1f}x)"


#: issue 16: decode + triangulate of one full view, median, ms
TOTAL_BOUND_MS = 100
#: issue 32: the same, ms, and its ratio to the plain numpy integer decoder of the same frames
ISSUE32_MS, ISSUE32_RATIO = 30, 1.1


def print_reconstruct(d: dict[str, Any], baseline: dict[str, Any]) -> None:
    w, h = d["camera_px"]
    print(f"\n== 2. reconstruct_view of one view ({w}x{h} px, {d['frames']} frames, frames in "
          f"memory; min / median of {d['repeats']}, ms) ==")
    print(f"  simulator render of the view: {d['render_s']:.1f} s (not timed below)")
    cores = f"{d['threads']} threads (dotshell)"
    print(f"  {'':16s} {cores:>26s} {'1 thread':>22s}")
    for stage in ("decode", "triangulate", "total"):
        every, one = d[f"{stage}_cores"], d[f"{stage}_one"]
        print(f"  {stage:16s} {every['min'] * 1e3:12.1f} / {every['median'] * 1e3:9.1f}"
              f"   {one['min'] * 1e3:9.1f} / {one['median'] * 1e3:9.1f}"
              + _vs(every["median"], baseline.get(f"{stage}_ms")))
    if "numpy" in d:
        numpy_ms, cpu = d["numpy"]["median"] * 1e3, d["cpu_cores"]["median"] * 1e3
        print(f"  {'numpy integer':16s} {d['numpy']['min'] * 1e3:12.1f} / {numpy_ms:9.1f}"
              f"   (plain numpy decoder of the same frames, interleaved)")
        print(f"  CPU of a view (every thread) {cpu:.1f} ms on {d['threads']} threads, "
              f"{d['cpu_one']['median'] * 1e3:.1f} ms on 1; numpy decoder "
              f"{d['cpu_numpy']['median'] * 1e3:.1f} ms")
    total = d["total_cores"]["median"] * 1e3
    print(f"  decode + triangulate median {total:.1f} ms: "
          f"{'within' if total <= TOTAL_BOUND_MS else 'ABOVE'} issue 16's {TOTAL_BOUND_MS} ms"
          + (f", {'within' if total <= ISSUE32_MS else 'ABOVE'} issue 32's {ISSUE32_MS} ms; "
             f"{total / numpy_ms:.2f}x the numpy decoder (issue 32: <= {ISSUE32_RATIO})"
             if "numpy" in d else ""))
    print(f"  {d['decoded_px']} px decoded, {d['points']} points in the ROI")


# ---- 4. end-to-end scan and reconstruct --------------------------------------------------------

STAGES = ("acquire", "decode", "triangulate", "merge", "validate", "previews")


def print_scan(s: dict[str, Any], baseline: dict[str, Any]) -> None:
    rep, (w, h) = s["report"], s["camera"]
    t = rep.get("timings_s", {})
    print(f"\n== 4. end-to-end demo scan ({s['views']} views, camera {w}x{h} px; "
          f"status {s['status']}) ==")
    print(f"  wall {s['wall_s']:.1f} s in scan(); process incl. start-up "
          f"{s['process_wall_s']:.1f} s")
    for k in [*STAGES, *(k for k in t if k not in STAGES)]:
        label = "acquire (render+stage+write)" if k == "acquire" else k
        print(f"  {label:28s} {t.get(k, float('nan')):8.2f} s")
    other = s["wall_s"] - sum(t.get(k, 0.0) for k in t)
    print(f"  {'other (set-up, PLY, report)':28s} {other:8.2f} s")
    before = baseline.get("scan_peak_rss_mib")
    print(f"  peak RSS of the scan process {s['peak_rss_mib']:.0f} MiB (getrusage ru_maxrss)"
          + (f"; baseline {before:.0f} MiB" if before else ""))
    v = rep.get("validation", {})
    print(f"  points {rep.get('cloud', {}).get('points')}; radius error "
          f"mean {v.get('mean_rel_error_pct', float('nan')):.3f} % "
          f"std {v.get('std_rel_error_pct', float('nan')):.3f} %; "
          f"coverage {v.get('coverage_pct', float('nan')):.1f} %")


def print_reconstruct_run(r: dict[str, Any], baseline: dict[str, Any]) -> None:
    t = r["report"].get("timings_s", {})
    before = {k: baseline.get(k) for k in ("reconstruct_wall_s", "reconstruct_peak_rss_mib")}
    print(f"\n== 5. reconstruct of that run from its frames on disk ({r['views']} views) ==")
    print(f"  wall {r['wall_s']:.1f} s in reconstruct_run()"
          + (f" (baseline {before['reconstruct_wall_s']:.1f} s)"
             if before["reconstruct_wall_s"] else "")
          + "; " + ", ".join(f"{k} {v:.2f} s" for k, v in t.items()))
    print(f"  peak RSS {r['peak_rss_mib']:.0f} MiB"
          + (f" (baseline {before['reconstruct_peak_rss_mib']:.0f} MiB)"
             if before["reconstruct_peak_rss_mib"] else ""))


# ---- main -----------------------------------------------------------------------------------

def ensure_contrib_venv() -> Path:
    """Python of ``.venv-bench-contrib`` with numpy + opencv-contrib-python-headless; created
    (and cached) on first use."""
    py = CONTRIB_VENV / "bin" / "python"
    probe = [str(py), "-c", "import cv2, numpy; cv2.structured_light.GrayCodePattern"]
    if py.exists() and subprocess.run(probe, capture_output=True).returncode == 0:
        return py
    print(f"creating {CONTRIB_VENV.name} (numpy, opencv-contrib-python-headless) ...", flush=True)
    subprocess.run(["python3", "-m", "venv", str(CONTRIB_VENV)], check=True)
    subprocess.run([str(py), "-m", "pip", "install", "-q", "numpy",
                    "opencv-contrib-python-headless"], check=True)
    subprocess.run(probe, check=True)
    return py


def load_baseline(quick: bool) -> dict[str, Any]:
    """The recorded figures before issue 16 (empty for ``--quick``: they are full-resolution)."""
    if quick or not BASELINE.is_file():
        return {}
    return json.loads(BASELINE.read_text())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true",
                    help="camera 320x256, projector 256x192, 2 views (tests the harness)")
    ap.add_argument("--repeats", type=int, default=5, help="repeats of each timing (min, median)")
    ap.add_argument("--skip-scan", action="store_true", help="sections 1 to 3 only")
    ap.add_argument("--skip-tui", action="store_true", help="without the idle-TUI section")
    ap.add_argument("--skip-batch", action="store_true",
                    help="no section 7 (12 runs serially vs a 2-worker Dask cluster)")
    args = ap.parse_args()
    configure_process()  # as the dotshell command runs
    pm = get_plugin_manager()
    profile = load_bench_profile(pm, args.quick)
    baseline = load_baseline(args.quick)
    results: dict[str, Any] = {"quick": args.quick, "machine": {
        "python": platform.python_version(), "cpus": os.cpu_count(),
        "numpy": np.__version__, "opencv": cv2.__version__,
        "loadavg_1min_start": os.getloadavg()[0]}}
    print(f"dotshell bench ({'quick' if args.quick else 'full resolution'}); {os.cpu_count()} "
          f"cores, 1-min load average at start {os.getloadavg()[0]:.2f}")
    if baseline:
        print(f"baseline: {baseline['recorded']}")
    with tempfile.TemporaryDirectory(prefix="dotshell-bench-") as tmp:
        work = Path(tmp)
        view = render_view(profile, pm)
        results["frame_io"] = frame_io.measure(view.frames, view.names, work, args.repeats)
        frame_io.print_frame_io(results["frame_io"])
        results["reconstruct_view"] = time_reconstruct(view, profile.data["processing"],
                                                       args.repeats)
        print_reconstruct(results["reconstruct_view"], baseline)
        peer = decoders.OpenCVPeer(ensure_contrib_venv(), view.frames, view.names,
                                   view.projector_size, view.bit_depth, work)
        integer = make_coding(profile, pm, subpixel=False)
        results["decoders"] = decoders.compare(view, integer, peer, args.repeats,
                                               profile.role("coding")["settings"],
                                               lambda **o: make_coding(profile, pm, **o))
        decoders.print_decoders(results["decoders"], baseline)
        del view, peer
        if not args.skip_scan:
            results["scan"] = run_child("scan", work / "runs", args.quick, work)
            print_scan(results["scan"], baseline)
            results["reconstruct_run"] = run_child("reconstruct",
                                                   Path(results["scan"]["run_dir"]),
                                                   args.quick, work)
            print_reconstruct_run(results["reconstruct_run"], baseline)
            results["mesh_run"] = run_child("mesh", Path(results["scan"]["run_dir"]),
                                            args.quick, work)
            print(f"\n== 5b. dotshell mesh of that run: wall {results['mesh_run']['wall_s']:.1f}"
                  f" s, CPU {results['mesh_run']['cpu_s']:.1f} s, peak RSS "
                  f"{results['mesh_run']['peak_rss_mib']:.0f} MiB ==")
        results["acquisition_rate"] = acquisition_rate.measure(pm, work / "acquisition")
        acquisition_rate.print_rates(results["acquisition_rate"])
        if not args.skip_tui:
            from bench_tui import print_tui, run_tui_bench

            results["tui"] = run_tui_bench(args.quick)
            print_tui(results["tui"])
        if not args.skip_scan and not args.skip_batch:
            results["batch"] = batch_bench.bench_batch(Path(results["scan"]["run_dir"]), work,
                                                       args.quick)
            batch_bench.print_batch(results["batch"])
        results["forward"] = forward_bench.measure(work, args.quick, args.repeats,
                                                   args.repeats if args.quick else 2)
        forward_bench.print_forward(results["forward"])
        results["cli"] = issue32.measure_cli()
        issue32.print_table(results)
    results["machine"]["loadavg_1min_end"] = os.getloadavg()[0]
    print(f"\n1-min load average at end {os.getloadavg()[0]:.2f} (other work on the machine "
          "skews every figure above; the sides of each comparison ran interleaved)")
    out = RESULTS.with_name("latest-quick.json") if args.quick else RESULTS
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(results, indent=2, default=str))
    print(f"\nwritten {out.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
