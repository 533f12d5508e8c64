"""`dotshell calibrate --captures`: calibration from pose folders captured anywhere, here by the
simulated rig with the projector ABOVE the camera (profiles/sim-metal-cylinder-vertical.toml)
showing OpenCV's GrayCodePattern sequence (tests/opencv_graycode.py) under OpenCV's file names —
5 poses, no turntable frames — then a turntable set with wrong stage angles, refused with its
RMS.

The fast tests run at 0.2× (256×205 camera, a 3 mm board); the issue's limits (focal lengths and
baseline within 0.2 % of the truth) are checked at full resolution (slow, `make validate`).
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import pytest

import opencv_graycode
from conftest import ROOT
from dotshell.calibration.board import Board
from dotshell.calibration.captures import calibrate_captures
from dotshell.calibration.procedure import compare_to_truth
from dotshell.profile.calibration import CALIBRATE_SCHEMA
from dotshell.cli.app import main
from dotshell.geometry.calibration import RigCalibration
from dotshell.settings import validate_settings
from sim_sequences import connected_rig, render_board_poses, render_turntable

#: Five of the reference bench's free poses (rolled, tilted and panned up to 40°).
POSES = [1, 2, 3, 4, 5]
TURNTABLE_POSE = [15.0, -30.0, 0.0, 0.0, 0.0, 16.0]
TRUE_ANGLES = [-30.0, 0.0, 30.0]


def _captures(tmp: Path, factor: float) -> tuple[dict, Board, list[Path], Path, Path]:
    """Pose folders in OpenCV's order, turntable frames, a layout for the projector size."""
    from dotshell_sim.bench import scale_profile

    raw = tomllib.loads((ROOT / "profiles" / "sim-metal-cylinder-vertical.toml").read_text())
    poses = tomllib.loads((ROOT / "profiles" / "sim-metal-cylinder.toml").read_text())
    poses = [poses["calibrate"]["poses"][i] for i in POSES]
    rig = connected_rig(scale_profile(raw, factor) if factor != 1 else raw)
    # at 0.2x the 2 mm squares would be 13 px: a coarser print of the same size
    board = Board("checkerboard", 15, 11, 2.0) if factor == 1 else Board("checkerboard", 10, 7, 3.0)
    pw, ph = rig["projector"].resolution
    dirs = render_board_poses(rig, board.sim_dict(), poses,
                              opencv_graycode.capture_sequence(pw, ph), tmp / "poses",
                              opencv_graycode.file_name)
    turn = render_turntable(rig, board.sim_dict(), TURNTABLE_POSE, TRUE_ANGLES, tmp / "turntable")
    return rig, board, dirs, turn, opencv_graycode.layout_file(tmp / "opencv.toml", (pw, ph))


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    return _captures(tmp_path_factory.mktemp("calcap"), 0.2)


def _errors(result, rig) -> dict:
    return compare_to_truth(result.calibration, rig["camera"].ground_truth_calibration())


def test_five_opencv_poses_without_turntable(captures, tmp_path, pm):
    rig, board, dirs, _, layout = captures
    settings = validate_settings(CALIBRATE_SCHEMA, {}, "defaults")
    res = calibrate_captures(dirs, layout, board, pm, settings, tmp_path)
    g = _errors(res, rig)
    print(json.dumps({k: g[k] for k in ("camera", "projector", "baseline_pct")}),
          res.report["rms_px"])
    assert not any(res.report["left_out"].values())  # all five poses used
    # 256x205 camera (measured with distortion = "auto": focal 0.08-0.10 % camera, 0.02 %
    # projector, baseline 0.003 %); the 0.2 % is held at full resolution (slow test)
    for w in ("camera", "projector"):
        assert max(abs(g[w]["fx_pct"]), abs(g[w]["fy_pct"])) < 0.6
    assert abs(g["baseline_pct"]) < 0.6
    # five poses in a narrow field: the projector's richer models fit k2 = -500 against
    # k3 = 60 000 (terms not determined) and predicted held-out poses best; they are not chosen
    # (with "full" the projector's cy was 6.2 px off and the baseline 0.075 %; now 2.5 px)
    model = res.report["model"]["projector"]
    assert model["model"] == "k1" and "determined" in model["reason"]
    full = next(c for c in model["candidates"] if c["model"] == "full")
    assert full["undetermined"]
    assert max(abs(g["projector"]["cx_px"]), abs(g["projector"]["cy_px"])) < 4.0
    run = res.run_dir
    cap = json.loads((run / "capture.json").read_text())
    assert cap["layout"]["layout"]["name"] == "opencv-graycode" and len(cap["poses"]) == 5
    assert cap["poses"][0]["frames"][0].endswith("pose1/pattern_cam1_im1.png")
    cal = RigCalibration.load(run / "calibration.json")
    assert not cal.axis_measured and "turntable" not in cal.rms
    assert "no turntable" in res.report["turntable"] and res.report["coding"]["layout"]


def test_bad_turntable_set_is_refused_with_its_rms(captures, tmp_path, capsys):
    """The stage angles given do not match the images (they are 15° apart, the stage turned
    30°): the axis is refused with its RMS, and no calibration is written."""
    _, _, dirs, turn, layout = captures
    code = main(["calibrate", "--captures", *map(str, dirs), "--layout", str(layout),
                 "--board", "10x7", "--square", "3", "--turntable", str(turn),
                 "--turntable-angles", "-15", "0", "15", "--board-height", "16",
                 "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert code == 2 and "calibration refused" in err
    assert "turntable axis RMS" in err and "max_rms_px 1 px" in " ".join(err.split())
    (run,) = tmp_path.iterdir()
    refused = json.loads((run / "calibration-refused.json").read_text())
    assert refused["rms_px"]["turntable"] > 1.0 and refused["refused"]
    assert not (run / "calibration.json").exists() and not (run / "calibration.yml").exists()


def test_captures_needs_the_target_and_a_layout_with_rows(captures, tmp_path, capsys):
    _, _, dirs, _, layout = captures
    assert main(["calibrate", "--captures", str(dirs[0]), "--layout", str(layout)]) == 2
    assert "--board COLSxROWS --square MM" in capsys.readouterr().err
    assert main(["calibrate", "--captures", str(dirs[0]), "--layout", "slstudio-graycode",
                 "--board", "10x7", "--square", "3", "--out", str(tmp_path)]) == 2
    assert "has no rows" in capsys.readouterr().err


@pytest.mark.slow
def test_five_opencv_poses_full_resolution(tmp_path, pm):
    """The issue's acceptance: focal lengths and baseline within 0.2 % of the truth."""
    rig, board, dirs, _, layout = _captures(tmp_path, 1.0)
    settings = validate_settings(CALIBRATE_SCHEMA, {}, "defaults")
    res = calibrate_captures(dirs, layout, board, pm, settings, tmp_path / "runs")
    g = _errors(res, rig)
    print(json.dumps({"errors": {k: g[k] for k in ("camera", "projector", "baseline_pct",
                                                   "rotation_deg")},
                      "rms_px": res.report["rms_px"], "sigma": res.report["sigma"]}, indent=1))
    for w in ("camera", "projector"):
        assert max(abs(g[w]["fx_pct"]), abs(g[w]["fy_pct"])) <= 0.2
    assert abs(g["baseline_pct"]) <= 0.2
