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

from dotshell.cli.decode import (
    add_layout_arg,
    loss_notes,
    pixel_counts,
    quality_line,
    refuse_layout_overrides,
)
from dotshell.cli.common import print_as_is


def add_captures_args(sp: argparse.ArgumentParser) -> None:
    """Options of ``dotshell reconstruct`` for captures made elsewhere."""
    sp.add_argument("--captures", metavar="DIR",
                    help="reconstruct the image sequence in DIR (made by another rig or program) "
                         "instead of a run; needs --calibration and --layout")
    add_layout_arg(sp)
    sp.add_argument("--captures2", metavar="DIR",
                    help="a second camera's sequence of the same projector patterns: with "
                         "--camera-pair, camera 1 (--captures) is triangulated against camera 2 "
                         "through the projector codes (the projector needs no calibration); "
                         "with --calibration (camera 1 and the projector) too, the "
                         "camera-projector and camera-camera points are fused")
    sp.add_argument("--camera-pair", metavar="FILE",
                    help="camera-pair.json of the two cameras (dotshell calibrate --camera-pair)")
    sp.add_argument("--layout2", metavar="LAYOUT",
                    help="layout of --captures2 when it differs from --layout (e.g. other file "
                         "names)")
    sp.add_argument("--reference", metavar="FILE",
                    help="reference cloud (.ply, or .mat with xyz) to measure the result against")
    sp.add_argument("--coverage-radius", type=float, default=1.0, metavar="MM",
                    help="a reference point counts as covered within this distance (mm)")
    sp.add_argument("--out", default="runs", help="parent directory of the output (default: runs)")


def reconstruct_captures_command(args: argparse.Namespace, pm, out: Console) -> int:
    from dotshell.errors import RunError
    from dotshell.pipeline.captures import reconstruct_captures

    if args.captures2 or args.camera_pair:
        return camera_pair_command(args, pm, out)
    missing = [flag for flag, v in (("--captures", args.captures), ("--calibration",
               args.calibration), ("--layout", args.layout)) if not v]
    if missing:
        raise RunError(f"dotshell reconstruct needs a RUN directory, or --captures DIR "
                       f"--calibration FILE --layout LAYOUT; missing: {', '.join(missing)}.")
    res = reconstruct_captures(args.captures, args.calibration, args.layout, pm, args.out,
                               reference=args.reference, coverage_radius_mm=args.coverage_radius)
    r = res.report
    counts = {**r["decode"], "grazing": r.get("grazing", 0),
              "row_rejected": r.get("row_rejected", 0)}
    out.print(pixel_counts(counts))
    out.print(f"  {quality_line(r['quality'])}")
    for line in loss_notes(counts, r["quality"]):
        print_as_is(out, f"  {line}")
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
        print_as_is(out, f"preview {name}: {res.out_dir / rel}")
    if r.get("preview_warning"):
        out.print(f"[yellow]warning:[/] {escape(r['preview_warning'])}")
    print_as_is(out, f"output: {res.out_dir}  (cloud.ply, report.json)")
    return 0


def camera_pair_command(args: argparse.Namespace, pm, out: Console) -> int:
    """``reconstruct --captures DIR1 --captures2 DIR2 --camera-pair FILE --layout L``
    [``--calibration FILE``: camera 1 and the projector, to fuse the two triangulations]."""
    from dotshell.errors import RunError
    from dotshell.pipeline.camera_pair import reconstruct_camera_pair

    missing = [flag for flag, v in (("--captures", args.captures), ("--captures2",
               args.captures2), ("--camera-pair", args.camera_pair), ("--layout", args.layout))
               if not v]
    if missing:
        raise RunError("two cameras sharing one projector need --captures DIR1 --captures2 DIR2 "
                       f"--camera-pair FILE --layout LAYOUT; missing: {', '.join(missing)}.")
    res = reconstruct_camera_pair(args.captures, args.captures2, args.camera_pair, args.layout,
                                  args.layout2, pm, args.out,
                                  calibration=args.calibration)
    r = res.report
    for name, counts, q in zip(("camera 1", "camera 2"), r["decode"], r["quality"]):
        out.print(f"{name}: {pixel_counts(counts)}")
        out.print(f"  {quality_line(q)}")
    gap = r["ray_gap_mm"]
    out.print(f"{r['matches']} pixels matched by projector code; {r['cloud']['points']} points "
              f"(camera 1 frame, mm); median ray gap {gap['median']:.4f} mm, {gap['dropped']} "
              f"dropped over {gap['dropped_over']:g} mm")
    if "fusion" in r:
        f = r["fusion"]
        out.print(f"fused with the calibrated projector: camera 2 spans "
                  f"{f['camera2_px_per_projector_px']:.2f} px per projector px, camera–camera "
                  f"depth σ {f['depth_sigma_ratio_camera_camera_over_projector']:.2f}× "
                  "camera–projector's; camera-projector.ply and camera-camera.ply hold the "
                  "single estimates")
    print_as_is(out, f"output: {res.out_dir}  (cloud.ply, report.json)")
    return 0


def add_calibrate_parser(sub, profile_args=None) -> None:
    """``dotshell calibrate``; its own arguments (the profile is optional with --solve and
    --captures, so the shared ``profile_args`` are not used)."""
    sp = sub.add_parser("calibrate", help="capture the calibration target and solve camera, "
                        "projector, their pose and the turntable axis; or solve pose folders "
                        "captured anywhere (--captures)")
    sp.add_argument("profile", nargs="?",
                    help="profile TOML: its [calibrate] settings and, to capture, its devices "
                         "(optional with --solve and --captures: defaults then)")
    sp.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a setting (TOML value), e.g. --set calibrate.min_poses=5")
    sp.add_argument("--out", default="runs", help="parent directory of the calibration run")
    sp.add_argument("--solve", metavar="RUN",
                    help="solve an existing calibration run (its frames on disk) instead of "
                         "capturing")
    sp.add_argument("--captures", nargs="+", metavar="DIR",
                    help="pose folders captured anywhere, one pose's whole sequence each "
                         "(needs --layout, and --board/--square without a profile)")
    add_layout_arg(sp, "the pose folders' sequence")
    sp.add_argument("--board", metavar="COLSxROWS",
                    help="target squares across x down (not inner corners), e.g. 15x11")
    sp.add_argument("--square", type=float, metavar="MM", help="side of a square (mm)")
    sp.add_argument("--target", choices=("checkerboard", "charuco"),
                    help="printed target (default: checkerboard)")
    sp.add_argument("--marker", type=float, metavar="MM", help="ChArUco marker side (mm)")
    sp.add_argument("--dictionary", metavar="NAME",
                    help="ChArUco ArUco dictionary (default DICT_4X4_50)")
    sp.add_argument("--camera-only", nargs="+", metavar="IMAGE_OR_DIR",
                    help="calibrate the camera alone from plain photos of the board (files, or "
                         "folders of them; needs --board/--square without a profile)")
    sp.add_argument("--camera-pair", nargs=2, metavar=("DIR1", "DIR2"),
                    help="calibrate two cameras and their pose from board photos both took "
                         "(one photo per pose in each folder, paired in name order); writes "
                         "camera-pair.json for reconstruct --captures2")
    sp.add_argument("--turntable", metavar="DIR",
                    help="white frames of the board on the stage, one per stage angle (name "
                         "order); solves the turntable axis (optional)")
    sp.add_argument("--turntable-angles", nargs="+", type=float, metavar="DEG",
                    help="stage angle of each --turntable image (degrees)")
    sp.add_argument("--board-height", type=float, metavar="MM",
                    help="height of the board centre above the stage plate for --turntable")
    sp.set_defaults(func=cmd_calibrate)


def calibrate_settings(args: argparse.Namespace, pm):
    """([calibrate] settings, profile or None): the profile's section with --set applied, or
    the defaults with --set applied; then the board options."""
    from dotshell.profile.calibration import CALIBRATE_SCHEMA
    from dotshell.errors import ProfileError
    from dotshell.profile.loader import apply_overrides, load_profile
    from dotshell.settings import validate_settings

    refuse_layout_overrides(args.set, getattr(args, "layout", None))
    profile = None
    if args.profile:
        profile = load_profile(args.profile, pm, args.set)
        settings = profile.calibrate.as_table()
    else:
        raw = apply_overrides({}, args.set, "--set")
        other = [k for k in raw if k != "calibrate"]
        if other:
            raise ProfileError(f"--set {other[0]}.…: without a profile only calibrate.KEY=VALUE "
                               "settings apply.")
        settings = validate_settings(CALIBRATE_SCHEMA, raw.get("calibrate", {}), "--set")
    if args.board:
        try:
            cols, rows = (int(x) for x in args.board.lower().split("x"))
        except ValueError:
            raise ProfileError(f"--board {args.board!r}: give squares across x down, e.g. "
                               "15x11.") from None
        settings.update(columns=cols, rows=rows)
    for key, value in (("square_mm", args.square), ("target", args.target),
                       ("marker_mm", args.marker), ("dictionary", args.dictionary)):
        if value is not None:
            settings[key] = value
    return validate_settings(CALIBRATE_SCHEMA, settings, "calibrate"), profile


def cmd_calibrate(args: argparse.Namespace) -> int:
    from dotshell.calibration.board import Board
    from dotshell.calibration.captures import TurntableFrames, calibrate_captures
    from dotshell.calibration.procedure import capture, solve
    from dotshell.cli.common import ScanProgress, err, out, plugin_manager
    from dotshell.errors import CalibrationError
    from dotshell.events import EventBus

    pm = plugin_manager(args)
    settings, profile = calibrate_settings(args, pm)
    bus = EventBus()
    view = ScanProgress(err)
    bus.subscribe(view)

    def ask(message: str) -> None:
        input(f"{message}\nPress Enter when the board is in place... ")

    if args.camera_only:
        return camera_only_command(args, settings, profile, out)
    if args.camera_pair:
        return camera_pair_calibration_command(args, settings, profile, out)
    with view.progress:
        if args.captures:
            if not args.layout:
                raise CalibrationError("calibrate --captures needs --layout LAYOUT (the order the "
                                       "pose folders' frames were captured in).")
            if not (args.board or profile) or not (args.square or profile):
                raise CalibrationError("calibrate --captures needs the target: --board COLSxROWS "
                                       "--square MM (or a profile's [calibrate]).")
            turntable = None
            if args.turntable:
                if not args.turntable_angles or args.board_height is None:
                    raise CalibrationError("--turntable needs --turntable-angles DEG ... (one per "
                                           "image) and --board-height MM.")
                turntable = TurntableFrames(Path(args.turntable), tuple(args.turntable_angles),
                                            args.board_height)
            result = calibrate_captures(args.captures, args.layout, Board.from_settings(settings),
                                        pm, settings, args.out, turntable, bus)
        elif args.solve:
            result = solve(Path(args.solve), settings, pm, bus)
        elif profile is None:
            raise CalibrationError("dotshell calibrate needs a PROFILE to capture with, or "
                                   "--solve RUN, or --captures DIR ... --layout LAYOUT.")
        else:
            result = solve(capture(profile, pm, args.out, bus, ask), settings, pm, bus)
    print_coding(result.report["coding"], profile, out)
    print_calibration(result.report, result.calibration, out)
    run = result.run_dir
    print_as_is(out, f"calibration: {run / 'calibration.json'} (and calibration.yml for OpenCV)")
    if profile is not None:
        print_as_is(out, f"use it: dotshell scan {args.profile} --calibration "
                         f"{run / 'calibration.json'}")
    return 0


def camera_only_command(args: argparse.Namespace, settings: dict[str, Any], profile,
                        out: Console) -> int:
    """``dotshell calibrate --camera-only``: the camera from plain board photos."""
    from dotshell.calibration.board import Board
    from dotshell.calibration.camera_only import calibrate_camera
    from dotshell.errors import CalibrationError

    if not (args.board or profile) or not (args.square or profile):
        raise CalibrationError("calibrate --camera-only needs the target: --board COLSxROWS "
                               "--square MM (or a profile's [calibrate]).")
    res = calibrate_camera(args.camera_only, Board.from_settings(settings), settings, args.out)
    r = res.report
    cells = [f"{k} {_value(r['coefficients'][k], k)}" for k in COEFFICIENT_KEYS]
    out.print("[bold]Camera[/] (value ± one-sigma; fx … cy in px): " + ", ".join(cells)
              + f"; RMS {r['rms_px']:.3f} px")
    m = r["model"]
    out.print(f"lens model: {m['model']} ({' '.join(m['terms'])}): {escape(m['reason'])}")
    out.print(f"corners cover {r['coverage_pct']:.0f} % of the image")
    for line in r["warnings"]:
        out.print(f"[yellow]warning:[/] {escape(line)}")
    for name, why in r["left_out"].items():
        out.print(f"[yellow]left out:[/] {name}: {escape(why)}")
    print_as_is(out, f"camera: {res.run_dir / 'camera.json'} (report: calibration-report.json, "
                     "report/residuals_*.png)")
    return 0


def camera_pair_calibration_command(args: argparse.Namespace, settings: dict[str, Any],
                                    profile, out: Console) -> int:
    """``dotshell calibrate --camera-pair DIR1 DIR2``: two cameras from board photos."""
    import numpy as np

    from dotshell.calibration.board import Board
    from dotshell.calibration.camera_only import calibrate_camera_pair
    from dotshell.errors import CalibrationError

    if not (args.board or profile) or not (args.square or profile):
        raise CalibrationError("calibrate --camera-pair needs the target: --board COLSxROWS "
                               "--square MM (or a profile's [calibrate]).")
    pair, run = calibrate_camera_pair(args.camera_pair[0], args.camera_pair[1],
                                      Board.from_settings(settings), settings, args.out)
    for name, lens in (("camera 1", pair.camera1), ("camera 2", pair.camera2)):
        K = lens.K
        out.print(f"{name}: fx {K[0, 0]:.2f}, fy {K[1, 1]:.2f}, cx {K[0, 2]:.2f}, cy "
                  f"{K[1, 2]:.2f} px, k1 k2 p1 p2 k3 {', '.join(f'{d:.4g}' for d in lens.dist)}")
    out.print(f"camera 2 from camera 1: baseline {float(np.linalg.norm(pair.T)):.3f} mm, joint RMS "
              f"{pair.rms_px:.3f} px over {len(pair.poses)} poses")
    print_as_is(out, f"camera pair: {run / 'camera-pair.json'}")
    return 0


def print_coding(coding: dict[str, Any], profile, out: Console) -> None:
    """Which coding decoded the frames: capture.json's, the one they were captured with."""
    settings = ", ".join(f"{k}={v}" for k, v in sorted(coding["settings"].items()))
    layout = f", frames in layout {coding['layout']!r}" if coding.get("layout") else ""
    out.print(f"decoded with {coding['backend']} ({escape(settings)}){layout}: the coding "
              "recorded in capture.json, the one the frames were captured with")
    if profile is not None:
        mine = profile.role("coding")
        if mine["backend"] != coding["backend"]:
            out.print(f"[yellow]note:[/] the profile's [coding] ({mine['backend']}) is not used "
                      "for these frames")


COEFFICIENT_KEYS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


def _value(entry: dict[str, Any], key: str) -> str:
    """``value ± sigma`` of a solved coefficient, ``0 (fixed)`` of one not solved."""
    v, s = entry["value"], entry["sigma"]
    if s is None:
        return "0 (fixed)" if v == 0 else f"{v:.4g} (fixed)"
    digits = 2 if key in ("fx", "fy", "cx", "cy") else 5
    return f"{v:.{digits}f} ± {s:.{digits}f}" if digits == 2 else f"{v:.4g} ± {s:.2g}"


def print_calibration(report: dict[str, Any], calib, out: Console) -> None:
    """The lenses with every coefficient and its one-sigma, the model chosen and why, the
    warnings with their fixes, the report's pictures, and the ground truth when there is one."""
    rms = report["rms_px"]
    coeffs = report.get("coefficients")
    out.print("[bold]Calibration[/] (value ± one-sigma of the joint solve; fx … cy in px)")
    for name, lens in (("camera", calib.camera), ("projector", calib.projector)):
        if coeffs:
            cells = [f"{k} {_value(coeffs[name][k], k)}" for k in COEFFICIENT_KEYS]
        else:
            values = (lens.K[0, 0], lens.K[1, 1], lens.K[0, 2], lens.K[1, 2], *lens.dist)
            cells = [f"{k} {v:.4g}" for k, v in zip(COEFFICIENT_KEYS, values)]
        out.print(f"  {name}: " + ", ".join(cells) + f"; RMS {rms[name]:.3f} px")
    out.print(f"camera–projector: baseline {calib.baseline_mm:.3f} mm, joint RMS "
              f"{rms['stereo']:.3f} px")
    sig = report.get("sigma")
    if sig:
        out.print(f"one-sigma of the baseline: ±{sig['baseline_mm']:.3f} mm")
    for which, m in (report.get("model") or {}).items():
        out.print(f"{which} lens model: {m['model']} ({' '.join(m['terms'])}): "
                  f"{escape(m['reason'])}")
    cov = report.get("coverage_pct")
    if cov:
        out.print(f"corners cover {cov['camera']:.0f} % of the camera image, "
                  f"{cov['projector']:.0f} % of the projector's")
    for line in report.get("warnings", []):
        out.print(f"[yellow]warning:[/] {escape(line)}")
    pics = report.get("residual_pictures")
    if pics:
        first = next(iter(pics.values()))
        out.print(f"residual vectors per pose: {len(pics)} pictures ({escape(first)} …) beside "
                  "calibration-report.json")
    d, p = calib.axis_direction, calib.axis_point
    if calib.axis_measured:
        out.print(f"turntable axis: direction ({d[0]:.5f}, {d[1]:.5f}, {d[2]:.5f}), plate point "
                  f"({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}) mm, RMS {rms['turntable']:.3f} px")
    else:
        out.print("turntable axis: not calibrated (no turntable frames); the calibration serves "
                  "single-view reconstruction, not turntable scans")
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
        if "axis_direction" in g["pass"]:
            row("axis direction", f"{g['axis_direction_deg']:.4f}°", "0.1°",
                g["pass"]["axis_direction"])
            row("axis position (⊥ distance)", f"{g['axis_point_mm']:.4f} mm", "0.1 mm",
                g["pass"]["axis_point"])
        if "axis_plate_offset" in g["pass"]:
            row("plate point along the axis", f"{g['axis_plate_offset_mm']:+.4f} mm", "0.1 mm",
                g["pass"]["axis_plate_offset"])
        out.print(gt)
