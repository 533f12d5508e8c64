"""dotshell benchmarks (``make bench``): speed and memory against a peer measured in the same run.

1. Decode + triangulation of one view (simulated reference bench, full resolution by default).
2. Peer: OpenCV contrib's ``GrayCodePattern.getProjPixel`` on the same frames, in its own venv
   (``.venv-bench-contrib``, created on first use; opencv-contrib conflicts with the project's
   opencv-python-headless).
3. End-to-end demo scan in a subprocess: wall time by stage, peak memory, accuracy.
4. A study of 12 copies of that scan re-processed serially vs by ``dotshell batch`` on a
   2-worker local Dask cluster, and a model of the scaling to N workers
   (:mod:`batch_bench`).

Prints the figures and writes them to ``bench-results/latest.json`` (``latest-quick.json``
with ``--quick``, so a harness test never replaces the full figures). ``--quick`` scales the
bench down (camera 320×256, projector 256×192, 2 views) to test the harness. Nothing here
asserts a speed.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from batch_bench import bench_batch, print_batch
from bench_profile import ROOT, load_bench_profile
from dotshell.coding import Correspondence, PatternCoding
from dotshell.devices import ExposureControl
from dotshell.geometry.calibration import RigCalibration
from dotshell.pipeline.reconstruct import reconstruct_view
from dotshell.plugins import PluginManager, get_plugin_manager
from dotshell.profile import Profile
from dotshell.rig import Rig
from dotshell_codings.graycode import code_offset

BENCH_DIR = Path(__file__).resolve().parent
CONTRIB_VENV = ROOT / ".venv-bench-contrib"
RESULTS = ROOT / "bench-results" / "latest.json"  # --quick writes latest-quick.json


@dataclass
class RenderedView:
    """One view's frames as written to and read back from PNG, with what decodes them."""

    angle_deg: float
    names: list[str]
    paths: list[Path]
    frames: list[np.ndarray]
    coding: PatternCoding
    calib: RigCalibration
    projector_size: tuple[int, int]
    bit_depth: int
    render_s: float
    write_s: float


# ---- 1. one view, dotshell ------------------------------------------------------------------

def render_view(profile: Profile, pm: PluginManager, frame_dir: Path) -> RenderedView:
    """Render view 0 with the simulator and save its frames as PNGs in ``frame_dir``.

    ``render_s`` is the simulator time (stage move + show + capture, seconds); ``write_s`` the
    PNG encoding and writing time (seconds). Frames are read back so both decoders see exactly
    the bytes on disk.
    """
    c = profile.role("coding")
    coding = pm.create("coding", c["backend"], c["settings"], None, profile.source)
    angle = profile.angles_deg()[0]
    captured, write_s, paths = [], 0.0, []
    with Rig(profile, pm) as rig:
        calib = rig.calibration()
        if isinstance(rig.camera, ExposureControl):
            rig.camera.set_exposure(profile.data["scan"]["exposure_ms"])
        patterns = coding.patterns(rig.projector.resolution)
        t0 = time.perf_counter()
        rig.stage.move_to(angle)
        for p in patterns:
            rig.projector.show(p.image)
            captured.append(rig.camera.capture())
        render_s = time.perf_counter() - t0
        projector_size, bit_depth = tuple(rig.projector.resolution), int(rig.camera.bit_depth)
    for i, (p, img) in enumerate(zip(patterns, captured)):
        t0 = time.perf_counter()
        path = frame_dir / f"{i:03d}_{p.name}.png"
        cv2.imwrite(str(path), img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        write_s += time.perf_counter() - t0
        paths.append(path)
    frames = [cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in paths]
    return RenderedView(angle, [p.name for p in patterns], paths, frames, coding, calib,
                        projector_size, bit_depth, render_s, write_s)


def time_dotshell(view: RenderedView, processing: dict[str, Any], repeats: int
                  ) -> tuple[dict[str, Any], Correspondence]:
    """Median decode / triangulate / total seconds of ``reconstruct_view`` over ``repeats``
    runs (frames already in memory), with the last run's correspondence."""
    runs = []
    for _ in range(repeats):
        vc = reconstruct_view(0, view.angle_deg, view.frames, view.coding, view.calib, processing)
        runs.append(vc.seconds)
    med = {k: statistics.median(r[k] for r in runs) for k in ("decode", "triangulate")}
    h, w = view.frames[0].shape
    return {"decode_s": med["decode"], "triangulate_s": med["triangulate"],
            "total_s": statistics.median(r["decode"] + r["triangulate"] for r in runs),
            "repeats": repeats, "decoded_px": int(vc.correspondence.valid.sum()),
            "points": int(len(vc.points)), "camera_px": [w, h], "frames": len(view.frames),
            "render_s": view.render_s, "png_write_s": view.write_s}, vc.correspondence


# ---- 2. the OpenCV peer ---------------------------------------------------------------------

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


def opencv_order(names: list[str]) -> list[int]:
    """Indices of our frames in OpenCV's order: each column bit's pattern and inverse (MSB
    first), the same for rows, then white and black. Ours: white, black, then the pairs; both
    codes light the stripe where the Gray bit is 1 in the non-inverse pattern."""
    pairs = [i for i, n in enumerate(names) if n.startswith("col_")] + \
            [i for i, n in enumerate(names) if n.startswith("row_")]
    return pairs + [names.index("white"), names.index("black")]


def run_peer(py: Path, view: RenderedView, work: Path, sample: int, seed: int) -> dict[str, Any]:
    """Decode ``sample`` random pixels with getProjPixel in the contrib venv; arrays + seconds."""
    job = {"frames": [str(view.paths[i]) for i in opencv_order(view.names)],
           "projector": list(view.projector_size), "shift": max(0, view.bit_depth - 8),
           "sample": sample, "seed": seed, "white_threshold": 5, "black_threshold": 40}
    (work / "peer_job.json").write_text(json.dumps(job))
    out = work / "peer_out.npz"
    subprocess.run([str(py), str(BENCH_DIR / "peer_opencv.py"), str(work / "peer_job.json"),
                    str(out)], check=True)
    with np.load(out) as z:
        return {k: z[k] for k in z.files}


def peer_figures(peer: dict[str, Any], corr: Correspondence, view: RenderedView,
                 dotshell_decode_s: float) -> dict[str, Any]:
    """Peer time scaled to the full image and column agreement with dotshell on the sample.

    OpenCV decodes the raw code value, dotshell the centred one: OpenCV column − ``col_offset``
    is compared with round(dotshell column). Rows are not compared (row offset ≠ 0 and OpenCV
    flags decoded rows past its height as errors)."""
    col_offset = code_offset(view.projector_size[0])
    h, w = view.frames[0].shape
    camera_px = w * h
    xs, ys, n = peer["xs"], peer["ys"], len(peer["xs"])
    seconds = float(peer["seconds"])
    full_s = seconds * camera_px / n
    ok_cv = ~peer["error"] & peer["lit"]
    err_lit = peer["error"] & peer["lit"]
    row_past = peer["row"] >= view.projector_size[1]
    ok_ds = corr.valid[ys, xs]
    both = ok_cv & ok_ds
    ours = np.rint(corr.column[ys, xs][both]).astype(np.int64)
    theirs = peer["col"][both].astype(np.int64) - col_offset
    return {"opencv_version": str(peer["cv2_version"]), "sample_px": n,
            "scale": camera_px / n, "sample_s": seconds, "per_px_us": seconds / n * 1e6,
            "full_image_s": full_s, "lit_only_s": full_s * float(peer["lit"].mean()),
            "ratio_vs_dotshell_decode": full_s / dotshell_decode_s,
            "opencv_decoded": int(ok_cv.sum()), "dotshell_decoded": int(ok_ds.sum()),
            "both_decoded": int(both.sum()),
            "opencv_errors_row_past_height": int((err_lit & row_past).sum()),
            "opencv_errors_other": int((err_lit & ~row_past).sum()),
            "opencv_shadow_dotshell_decoded": int((~peer["lit"] & ok_ds).sum()),
            "column_equal_pct": 100.0 * float((ours == theirs).mean()) if both.any() else None,
            "column_within_1_pct": (100.0 * float((abs(ours - theirs) <= 1).mean())
                                    if both.any() else None)}


# ---- 3. end-to-end scan -------------------------------------------------------------------------

def run_scan(quick: bool, work: Path) -> dict[str, Any]:
    """Run ``scan_child.py`` (a fresh process) and return its figures: wall seconds, peak RSS
    (MiB, the child's own ``getrusage`` maximum) and the scan report."""
    result = work / "scan_result.json"
    cmd = [sys.executable, str(BENCH_DIR / "scan_child.py"), str(work / "runs"), str(result)]
    t0 = time.perf_counter()
    subprocess.run(cmd + (["--quick"] if quick else []), check=True)
    out = json.loads(result.read_text())
    out["process_wall_s"] = time.perf_counter() - t0
    return out


# ---- printing -------------------------------------------------------------------------------

def print_view(d: dict[str, Any]) -> None:
    w, h = d["camera_px"]
    print(f"\n== 1. one view, dotshell reconstruct_view ({w}x{h} px, {d['frames']} frames, "
          f"median of {d['repeats']}) ==")
    print(f"  simulator render {d['render_s']:.2f} s, PNG write {d['png_write_s']:.2f} s "
          "(not part of the timing below)")
    print(f"  decode        {d['decode_s'] * 1e3:9.1f} ms")
    print(f"  triangulate   {d['triangulate_s'] * 1e3:9.1f} ms")
    print(f"  total         {d['total_s'] * 1e3:9.1f} ms   "
          f"({d['decoded_px']} px decoded, {d['points']} points in the ROI)")


def print_peer(p: dict[str, Any], decode_s: float) -> None:
    print(f"\n== 2. peer: OpenCV {p['opencv_version']} structured_light.GrayCodePattern"
          ".getProjPixel (same frames, 8 bit) ==")
    print(f"  timed on {p['sample_px']} random pixels (seed 0): {p['sample_s']:.2f} s "
          f"= {p['per_px_us']:.1f} us/px (one Python call per pixel, as the API is used)")
    print(f"  scaled x{p['scale']:.1f} to the full image: {p['full_image_s']:.1f} s "
          f"(lit pixels only, as OpenCV's decode() would call it: {p['lit_only_s']:.1f} s)")
    print(f"  ratio peer full image / dotshell decode ({decode_s * 1e3:.0f} ms): "
          f"{p['ratio_vs_dotshell_decode']:.0f}x")
    print(f"  sample decoded: OpenCV {p['opencv_decoded']}, dotshell {p['dotshell_decoded']}, "
          f"both {p['both_decoded']}")
    print(f"  OpenCV errors on lit pixels: {p['opencv_errors_row_past_height']} with the decoded "
          f"row past its height (our row code is centred), {p['opencv_errors_other']} other "
          "(a pattern/inverse pair < 5 DN apart, or column past its width); OpenCV shadow (white − black ≤ 40 DN) where "
          f"dotshell decodes: {p['opencv_shadow_dotshell_decoded']}")
    if p["column_equal_pct"] is not None:
        print(f"  columns only: OpenCV column == round(dotshell column) on "
              f"{p['column_equal_pct']:.2f} % of both-decoded pixels "
              f"(within ±1: {p['column_within_1_pct']:.2f} %)")


STAGES = ("acquire", "decode", "triangulate", "merge", "validate", "previews")


def print_scan(s: dict[str, Any]) -> None:
    rep, (w, h) = s["report"], s["camera"]
    t = rep.get("timings_s", {})
    print(f"\n== 3. end-to-end demo scan ({s['views']} views, camera {w}x{h} px; "
          f"status {s['status']}) ==")
    print(f"  wall {s['wall_s']:.1f} s in scan(); process incl. start-up "
          f"{s['process_wall_s']:.1f} s")
    for k in [*STAGES, *(k for k in t if k not in STAGES)]:
        label = "acquire (render+stage+PNG)" if k == "acquire" else k
        print(f"  {label:28s} {t.get(k, float('nan')):8.2f} s")
    other = s["wall_s"] - sum(t.get(k, 0.0) for k in t)
    print(f"  {'other (set-up, PLY, report)':28s} {other:8.2f} s")
    print(f"  peak RSS of the scan process {s['peak_rss_mib']:.0f} MiB "
          "(getrusage ru_maxrss, self and its children)")
    v = rep.get("validation", {})
    print(f"  points {rep.get('cloud', {}).get('points')}; radius error "
          f"mean {v.get('mean_rel_error_pct', float('nan')):.3f} % "
          f"std {v.get('std_rel_error_pct', float('nan')):.3f} %; "
          f"coverage {v.get('coverage_pct', float('nan')):.1f} %")


# ---- main -----------------------------------------------------------------------------------

def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true",
                    help="camera 320x256, projector 256x192, 2 views (tests the harness)")
    ap.add_argument("--repeats", type=int, default=5, help="reconstruct_view runs (median)")
    ap.add_argument("--sample", type=int, default=20000, help="pixels decoded by the peer")
    ap.add_argument("--skip-scan", action="store_true", help="sections 1 and 2 only")
    ap.add_argument("--skip-batch", action="store_true", help="no section 4 (the study batch)")
    args = ap.parse_args()
    pm = get_plugin_manager()
    profile = load_bench_profile(pm, args.quick)
    results: dict[str, Any] = {"quick": args.quick, "machine": {
        "python": platform.python_version(), "cpus": os.cpu_count(),
        "numpy": np.__version__, "opencv": cv2.__version__,
        "loadavg_1min_start": os.getloadavg()[0]}}
    print(f"dotshell bench ({'quick' if args.quick else 'full resolution'}); {os.cpu_count()} "
          f"cores, 1-min load average at start {os.getloadavg()[0]:.2f}")
    with tempfile.TemporaryDirectory(prefix="dotshell-bench-") as tmp:
        work = Path(tmp)
        (work / "frames").mkdir()
        view = render_view(profile, pm, work / "frames")
        results["view"], corr = time_dotshell(view, profile.data["processing"], args.repeats)
        print_view(results["view"])
        peer = run_peer(ensure_contrib_venv(), view, work, args.sample, seed=0)
        results["peer_opencv"] = peer_figures(peer, corr, view, results["view"]["decode_s"])
        print_peer(results["peer_opencv"], results["view"]["decode_s"])
        if not args.skip_scan:
            results["scan"] = run_scan(args.quick, work)
            print_scan(results["scan"])
            if not args.skip_batch:
                (scanned,) = [p for p in (work / "runs").iterdir() if p.is_dir()]
                results["batch"] = bench_batch(scanned, work, args.quick)
                print_batch(results["batch"])
    results["machine"]["loadavg_1min_end"] = os.getloadavg()[0]
    print(f"\n1-min load average at end {os.getloadavg()[0]:.2f} (other work on the machine "
          "skews every figure above; peer and dotshell ran back to back)")
    out = RESULTS.with_name("latest-quick.json") if args.quick else RESULTS
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(results, indent=2, default=str))
    print(f"\nwritten {out.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
