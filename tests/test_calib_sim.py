"""`dotshell calibrate` end to end on the simulated bench: the simulator renders the checkerboard
at the profile's poses, the solve is compared with the simulator's ground truth, and bad input
(wrong board, blurred pose, images of another size, too few poses) is named.

The fast tests run at 0.2× resolution with 6 free poses, 3 stage angles and a 3 mm board; the
full-resolution acceptance check (the issue's limits) and the metal-cylinder scan with the
measured calibration are marked slow (`make validate`).
"""

from __future__ import annotations

import json
import shutil
import tomllib
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import ROOT, small_profile_dict, write_profile
from dotshell.calibration.procedure import capture, solve
from dotshell.cli.app import main
from dotshell.errors import CalibrationError
from dotshell.geometry.calibration import RigCalibration
from dotshell.plugins import PluginManager
from dotshell.profile.loader import load_profile


def _pm() -> PluginManager:
    pm = PluginManager()
    pm.load_entry_points()
    return pm


@pytest.fixture(scope="module")
def small_capture(tmp_path_factory):
    """One reduced calibration capture, shared read-only (tests copy it to change it)."""
    tmp = tmp_path_factory.mktemp("calib")
    raw = small_profile_dict(0.2, 6)
    cal = raw["calibrate"]
    # at 0.2x the profile's 2 mm squares are 13 px, below what the sharpness estimate
    # measures: the reduced bench uses a coarser print of the same size (3 mm, 26 px squares)
    cal.update(columns=10, rows=7, square_mm=3.0)
    cal["poses"] = [cal["poses"][i] for i in (1, 2, 3, 4, 5, 6)]
    cal["turntable_angles_deg"] = [-30.0, 0.0, 30.0]
    cal["min_poses"] = 5
    prof = load_profile(write_profile(tmp / "small.toml", raw), _pm())
    run = capture(prof, _pm(), tmp / "runs")
    return prof, run


@pytest.fixture(scope="module")
def small_solution(small_capture):
    """The capture solved once (calibration.json written into it), for the tests that read the
    solve's result; the solve of each damaged copy and of the command line are their own."""
    prof, run = small_capture
    return solve(run, prof.data["calibrate"], _pm())


def _copy(run: Path, tmp: Path) -> Path:
    dst = tmp / "copy"
    shutil.copytree(run, dst, symlinks=True)
    return dst


def test_small_calibration_against_ground_truth(small_capture, small_solution):
    _, run = small_capture
    r = small_solution.report
    g = r["ground_truth"]
    print(json.dumps({k: r[k] for k in ("rms_px", "left_out", "ground_truth")}, indent=1))
    assert set(r["rms_px"]) == {"camera", "projector", "stereo", "turntable"}
    assert max(r["rms_px"].values()) < 0.2  # measured 0.04-0.08 px (edge-model corners)
    # 256x205 camera, 6 poses, 3 stage angles (measured: focal 0.02 % camera, 0.15 %
    # projector; principal points 0.8-1.8 px of these 5x coarser pixels; baseline 0.16 %;
    # axis 0.06° and 0.14 mm, 0.22 mm along); the limits are held at full resolution
    # (slow test). The principal points move with the noise's realization: over the camera
    # seeds 1-3, with the exact Poisson draw and the sensor's normal draw alike, they were off
    # by 0.1-5.4 px (issue 32, docs/performance.md), so the bound is 6 px
    for w in ("camera", "projector"):
        assert max(abs(g[w]["fx_pct"]), abs(g[w]["fy_pct"])) < 0.5
        assert max(abs(g[w]["cx_px"]), abs(g[w]["cy_px"])) < 6.0
    assert abs(g["baseline_pct"]) < 0.5
    assert g["axis_direction_deg"] < 0.2 and g["axis_point_mm"] < 0.4
    assert abs(g["axis_plate_offset_mm"]) < 0.6
    sig = r["sigma"]  # the joint solve's own one-sigma: the errors are within a few of it
    for w in ("camera", "projector"):
        assert abs(g[w]["cx_px"]) < 5 * sig[w]["cx"] and abs(g[w]["cy_px"]) < 5 * sig[w]["cy"]
    cal = RigCalibration.load(run / "calibration.json")
    assert cal.camera.size == (256, 205) and cal.rms["camera"] == r["rms_px"]["camera"]
    assert (run / "calibration.yml").is_file()
    for name in ("pose_00", "turntable_01"):
        assert name in r["poses"]


def test_small_cylinder_scan_with_measured_calibration(small_capture, small_solution,
                                                       tmp_path):
    from dotshell.pipeline.scan import scan

    prof, run = small_capture
    pm = _pm()
    measured = scan(prof, pm, tmp_path, calibration_file=str(run / "calibration.json"))
    vm = measured.report["validation"]
    print("measured calibration:", vm)  # measured 0.16 %; ground truth at this scale 0.12 %
    assert measured.report["calibration"].startswith("dotshell calibrate")
    assert vm["mean_rel_error_pct"] <= 0.4 and vm["coverage_pct"] >= 80.0


def test_wrong_board_size_names_the_images(small_capture, tmp_path):
    prof, run = small_capture
    run = _copy(run, tmp_path)
    cap = json.loads((run / "capture.json").read_text())
    cap["board"]["columns"] = 12  # the printed board has 10
    (run / "capture.json").write_text(json.dumps(cap))
    with pytest.raises(CalibrationError, match=r"was not found in any image: "
                       r"frames/pose_00/000_white.png.*columns and rows"):
        solve(run, prof.data["calibrate"], _pm())


def test_blurred_pose_is_left_out_and_named(small_capture, tmp_path):
    prof, run = small_capture
    run = _copy(run, tmp_path)
    p = run / "frames" / "pose_02" / "000_white.png"
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(p), cv2.GaussianBlur(img, (0, 0), 3.0))
    res = solve(run, prof.data["calibrate"], _pm())
    why = res.report["left_out"]["camera"]["pose_02"]
    assert "pose_02/000_white.png" in why and ("blurred" in why or "not found" in why)
    assert "pose_02" not in res.report["left_out"]["camera"] or \
        res.report["poses"]["pose_02"].get("camera_rms_px") is None
    settings = {**prof.data["calibrate"], "min_poses": 6}
    with pytest.raises(CalibrationError, match=r"camera: only 5 good poses.*pose_02"):
        solve(run, settings, _pm())


def test_mismatched_image_size_is_named(small_capture, tmp_path):
    prof, run = small_capture
    run = _copy(run, tmp_path)
    p = run / "frames" / "pose_01" / "005_col_01_inv.png"
    cv2.imwrite(str(p), np.zeros((100, 120), np.uint16))
    with pytest.raises(CalibrationError, match=r"pose_01/005_col_01_inv.png \(120x100\)"):
        solve(run, prof.data["calibrate"], _pm())


def test_cli_solves_a_capture_and_prints_truth(small_capture, capsys):
    """--solve needs no profile (the [calibrate] defaults) and says which coding decoded the
    frames: capture.json's, the one they were captured with."""
    _, run = small_capture
    code = main(["calibrate", "--solve", str(run)])
    text = " ".join(capsys.readouterr().out.split())
    assert code == 0
    assert "decoded with graycode (" in text and "axes=both" in text
    assert "recorded in capture.json" in text
    assert "Against the simulator's ground truth" in text and "axis direction" in text
    assert "turntable axis: direction" in text


def test_cli_error_without_poses(tmp_path, capsys):
    raw = small_profile_dict(0.2, 6)
    del raw["calibrate"]
    p = write_profile(tmp_path / "p.toml", raw)
    assert main(["calibrate", str(p), "--out", str(tmp_path)]) == 2
    assert "[calibrate] lists no poses" in capsys.readouterr().err


def test_charuco_target_is_rendered_and_found(tmp_path):
    from dotshell.calibration.board import Board, detect
    from dotshell_sim.bench import build_rig

    rig = build_rig(small_profile_dict(0.25, 1))
    for d in rig.values():
        d.connect()
    board = Board("charuco", 10, 7, 3.0, 2.2)
    rig["stage"].place_target(board.sim_dict(), {"rotation_deg": [0, -20, 10],
                                                 "centre_mm": [0, 0, 16]})
    rig["projector"].show(np.full((192, 256), 255, np.uint8))
    rig["camera"].set_exposure(10.0)
    det = detect(rig["camera"].capture(), board)
    assert det is not None and len(det.ids) >= 40
    truth = rig["camera"].ground_truth_calibration()
    from dotshell_sim.target import board_to_sample

    R, t = board_to_sample(board.sim_dict(), {"rotation_deg": [0, -20, 10], "centre_mm": [0, 0, 16]})
    X = board.object_points()[det.ids] @ R.T + t
    px = truth.camera.project(truth.sample_to_camera(X, 0.0))
    assert np.sqrt(np.mean(np.sum((px - det.pixels) ** 2, axis=1))) < 0.5


@pytest.mark.slow
def test_full_resolution_calibration_and_cylinder_scan(tmp_path):
    """The issue's acceptance: calibrate the reference bench, compare with the truth, then scan
    the metal cylinder with the measured calibration (mean radius error <= 0.5 %)."""
    from dotshell.pipeline.scan import scan

    pm = _pm()
    prof = load_profile(ROOT / "profiles" / "sim-metal-cylinder.toml", pm)
    run = capture(prof, pm, tmp_path)
    res = solve(run, prof.data["calibrate"], pm)
    g = res.report["ground_truth"]
    print(json.dumps({"ground_truth": g, "sigma": res.report["sigma"],
                      "rms_px": res.report["rms_px"]}, indent=1))
    assert not any(res.report["left_out"].values())  # every pose and stage angle used
    assert max(abs(g[w][k]) for w in ("camera", "projector") for k in ("fx_pct", "fy_pct")) <= 0.2
    assert max(abs(g[w][k]) for w in ("camera", "projector") for k in ("cx_px", "cy_px")) <= 1.0
    assert abs(g["baseline_pct"]) <= 0.2
    assert g["axis_direction_deg"] <= 0.1
    assert g["axis_point_mm"] <= 0.1  # perpendicular distance from the true axis, 0-40 mm
    assert abs(g["axis_plate_offset_mm"]) <= 0.1  # and the plate point along it
    assert all(g["pass"].values())
    result = scan(prof, pm, tmp_path, calibration_file=str(run / "calibration.json"))
    v = result.report["validation"]
    print(json.dumps(v, indent=1))
    assert result.report["calibration"].startswith("dotshell calibrate")
    assert v["mean_rel_error_pct"] <= 0.5
