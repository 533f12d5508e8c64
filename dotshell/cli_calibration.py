"""CLI front end of ``dotshell calibrate`` and ``dotshell reconstruct --captures`` (thin: parses
arguments, calls :mod:`dotshell.calibration.procedure` / :mod:`dotshell.pipeline.captures`,
prints tables)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.markup import escape
from rich.table import Table

from dotshell.cli_decode import add_decode_parser, pixel_counts  # noqa: F401 (for dotshell.cli)


def add_captures_args(sp: argparse.ArgumentParser) -> None:
    """Options of ``dotshell reconstruct`` for captures made elsewhere."""
    sp.add_argument("--captures", metavar="DIR",
                    help="reconstruct the image sequence in DIR (made by another rig or program) "
                         "instead of a run; needs --calibration and --layout")
    sp.add_argument("--layout", metavar="LAYOUT",
                    help="layout TOML of the sequence, or a shipped one: slstudio-graycode, "
                         "opencv-graycode")
    sp.add_argument("--reference", metavar="FILE",
                    help="reference cloud (.ply, or .mat with xyz) to measure the result against")
    sp.add_argument("--coverage-radius", type=float, default=1.0, metavar="MM",
                    help="a reference point counts as covered within this distance (mm)")
    sp.add_argument("--out", default="runs", help="parent directory of the output (default: runs)")


def reconstruct_captures_command(args: argparse.Namespace, pm, out: Console) -> int:
    from dotshell.errors import RunError
    from dotshell.pipeline.captures import reconstruct_captures

    missing = [flag for flag, v in (("--captures", args.captures), ("--calibration",
               args.calibration), ("--layout", args.layout)) if not v]
    if missing:
        raise RunError(f"dotshell reconstruct needs a RUN directory, or --captures DIR "
                       f"--calibration FILE --layout LAYOUT; missing: {', '.join(missing)}.")
    res = reconstruct_captures(args.captures, args.calibration, args.layout, pm, args.out,
                               reference=args.reference, coverage_radius_mm=args.coverage_radius)
    r = res.report
    out.print(pixel_counts({**r["decode"], "grazing": r.get("grazing", 0),
                            "row_rejected": r.get("row_rejected", 0)}))
    out.print(f"{r['cloud']['points']} points (camera frame, mm)")
    ref = r.get("reference")
    if ref:
        t = Table(title=escape(f"against {ref['path']} ({ref['reference_points']} points)"))
        for col in ("distance", "median", "mean", "RMS", "p90", "p95"):
            t.add_column(col)
        for key, label in (("to_reference_plane", "cloud → reference surface"),
                           ("to_reference_point", "cloud → nearest reference point"),
                           ("reference_to_points", "reference → nearest cloud point")):
            s = ref[key]
            if s:
                t.add_row(label, *(f"{s[k]:.3f} mm" for k in
                                   ("median_mm", "mean_mm", "rms_mm", "p90_mm", "p95_mm")))
        out.print(t)
        out.print(f"coverage: {ref['coverage_pct']:.2f} % of the reference points have a point "
                  f"within {ref['coverage_radius_mm']:g} mm; {ref['outside_reference']} points "
                  "lie where the reference has none")
    for name, rel in (r.get("previews") or {}).items():
        out.print(f"preview {name}: {res.out_dir / rel}")
    if r.get("preview_warning"):
        out.print(f"[yellow]warning:[/] {escape(r['preview_warning'])}")
    out.print(f"output: {res.out_dir}  (cloud.ply, report.json)")
    return 0


def add_calibrate_parser(sub, profile_args) -> None:
    sp = sub.add_parser("calibrate", help="capture the calibration target and solve camera, "
                        "projector, their pose and the turntable axis")
    profile_args(sp)
    sp.add_argument("--out", default="runs", help="parent directory of the calibration run")
    sp.add_argument("--solve", metavar="RUN",
                    help="solve an existing calibration run (its frames on disk) instead of "
                         "capturing")
    sp.set_defaults(func=cmd_calibrate)


def cmd_calibrate(args: argparse.Namespace) -> int:
    from dotshell.calibration.procedure import capture, solve
    from dotshell.cli import ScanProgress, _pm, err, out
    from dotshell.events import EventBus
    from dotshell.profile import load_profile

    pm = _pm(args)
    profile = load_profile(args.profile, pm, args.set)
    bus = EventBus()
    view = ScanProgress(err)
    bus.subscribe(view)

    def ask(message: str) -> None:
        input(f"{message}\nPress Enter when the board is in place... ")

    with view.progress:
        run = Path(args.solve) if args.solve else capture(profile, pm, args.out, bus, ask)
        result = solve(run, profile.data["calibrate"], pm, bus)
    print_calibration(result.report, result.calibration, out)
    out.print(f"calibration: {run / 'calibration.json'} (and calibration.yml for OpenCV)")
    out.print(f"use it: dotshell scan {args.profile} --calibration {run / 'calibration.json'}")
    return 0


def print_calibration(report: dict[str, Any], calib, out: Console) -> None:
    t = Table(title="Calibration")
    for col in ("", "fx [px]", "fy [px]", "cx [px]", "cy [px]", "k1", "k2", "RMS [px]"):
        t.add_column(col)
    rms = report["rms_px"]
    for name, lens in (("camera", calib.camera), ("projector", calib.projector)):
        K = lens.K
        t.add_row(name, f"{K[0, 0]:.2f}", f"{K[1, 1]:.2f}", f"{K[0, 2]:.2f}", f"{K[1, 2]:.2f}",
                  f"{lens.dist[0]:.4f}", f"{lens.dist[1]:.4f}", f"{rms[name]:.3f}")
    out.print(t)
    out.print(f"camera–projector: baseline {calib.baseline_mm:.3f} mm, joint RMS "
              f"{rms['stereo']:.3f} px")
    sig = report.get("sigma")
    if sig:
        c, p = sig["camera"], sig["projector"]
        out.print(f"one-sigma (joint solve covariance): camera cx ±{c['cx']:.2f}, cy "
                  f"±{c['cy']:.2f} px, fx ±{c['fx']:.2f} px; projector cx ±{p['cx']:.2f}, cy "
                  f"±{p['cy']:.2f} px, fx ±{p['fx']:.2f} px; baseline ±{sig['baseline_mm']:.3f} mm")
    d, p = calib.axis_direction, calib.axis_point
    out.print(f"turntable axis: direction ({d[0]:.5f}, {d[1]:.5f}, {d[2]:.5f}), plate point "
              f"({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}) mm, RMS {rms['turntable']:.3f} px")
    for what, left in report["left_out"].items():
        for name, why in left.items():
            out.print(f"[yellow]left out of the {what} solve:[/] {name}: {escape(why)}")
    g = report.get("ground_truth")
    if g:
        gt = Table(title="Against the simulator's ground truth")
        for col in ("quantity", "error", "limit", "ok"):
            gt.add_column(col)

        def row(label, value, limit, ok):
            gt.add_row(label, value, limit, "[green]yes[/]" if ok else "[red]NO[/]")

        for which in ("camera", "projector"):
            e = g[which]
            row(f"{which} fx, fy", f"{e['fx_pct']:+.4f} %, {e['fy_pct']:+.4f} %", "0.2 %",
                g["pass"][f"{which}_focal"])
            row(f"{which} cx, cy", f"{e['cx_px']:+.3f}, {e['cy_px']:+.3f} px", "1 px",
                g["pass"][f"{which}_principal_point"])
        row("baseline", f"{g['baseline_pct']:+.4f} %", "0.2 %", g["pass"]["baseline"])
        gt.add_row("rotation", f"{g['rotation_deg']:.4f}°", "", "")
        row("axis direction", f"{g['axis_direction_deg']:.4f}°", "0.1°", g["pass"]["axis_direction"])
        row("axis position (⊥ distance)", f"{g['axis_point_mm']:.4f} mm", "0.1 mm",
            g["pass"]["axis_point"])
        if "axis_plate_offset" in g["pass"]:
            row("plate point along the axis", f"{g['axis_plate_offset_mm']:+.4f} mm", "0.1 mm",
                g["pass"]["axis_plate_offset"])
        out.print(gt)
