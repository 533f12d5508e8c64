"""Captures from other rigs: layout files, frame ordering and polarity, SLStudio's calibration
import and its real skull capture (shared/data/slstudio-skull) against SLStudio's own cloud."""

from __future__ import annotations

import shutil
import subprocess
import tomllib
from pathlib import Path

import cv2
import numpy as np
import pytest

import opencv_graycode
from sim_sequences import connected_rig, render_sequence, true_projector_coordinates
from conftest import ROOT
from dotshell.cli.app import main
from dotshell.errors import CalibrationError, RunError
from dotshell.geometry.opencv_io import read_opencv_calibration, write_opencv_calibration
from dotshell.pipeline.captures import reconstruct_captures
from dotshell.run.capture_layouts import (capture_order, load_layout, read_captures, read_sequence,
                                  to_coding_frames)
from dotshell.plugins import PluginManager

SKULL = next((p / "shared" / "data" / "slstudio-skull" for p in (ROOT.parent, ROOT.parents[1])
              if (p / "shared" / "data" / "slstudio-skull").is_dir()),
             ROOT.parent / "shared" / "data" / "slstudio-skull")
needs_skull = pytest.mark.skipif(not (SKULL / "skull_gray").is_dir(),
                                 reason="shared/data/slstudio-skull is not present")


@pytest.fixture
def pm():
    m = PluginManager()
    m.load_entry_points()
    return m


def _opencv_sequence(tmp: Path, proj=(64, 16), cam=(200, 40)) -> tuple[Path, np.ndarray]:
    """OpenCV's capture sequence (tests/opencv_graycode.py) seen by a camera that sees the
    projector stretched; the directory and the true column of each camera column."""
    d = tmp / "caps"
    return d, opencv_graycode.write_stretched(d, proj, cam)


def _layout(tmp: Path, proj=(64, 16)) -> Path:
    return opencv_graycode.layout_file(tmp / "opencv.toml", proj)


@pytest.mark.parametrize("proj", [(64, 16), (100, 37)])
def test_opencv_layout_decodes_the_opencv_sequence(tmp_path, pm, proj):
    d, truth = _opencv_sequence(tmp_path, proj)
    layout = load_layout(_layout(tmp_path, proj))
    coding = pm.create("coding", "graycode", layout.coding_settings())
    names = coding.frame_names(layout.projector_size)
    order = capture_order(layout, names)
    n_col, n_row = (int(np.ceil(np.log2(s))) for s in proj)
    assert order[:2] == ["col_00", "col_00_inv"] and order[2 * n_col] == "row_00"
    assert order[-2:] == ["white", "black"] and len(order) == 2 + 2 * (n_col + n_row)
    frames = to_coding_frames(read_captures(d, layout, names), layout, names)
    corr = coding.decode(frames, layout.projector_size)
    assert corr.valid.mean() > 0.9
    err = np.abs(corr.column - truth[None, :])[corr.valid]
    assert np.median(err) < 0.3 and err.max() < 1.0  # right order, polarity and code offset
    wrong = load_layout(_layout(tmp_path, proj))  # same frames read with the opposite polarity
    object.__setattr__(wrong, "bright_is_one", False)
    bad = coding.decode(to_coding_frames(read_captures(d, wrong, names), wrong, names),
                        layout.projector_size)
    bad_err = np.abs(bad.column - truth[None, :])[bad.valid]
    assert bad.valid.mean() < 0.5 or np.median(bad_err) > 5


CONTRIB_PYTHON = ROOT / ".venv-bench-contrib" / "bin" / "python"


@pytest.mark.skipif(not CONTRIB_PYTHON.exists(),
                    reason=".venv-bench-contrib (opencv-contrib, made by `make bench`) is absent")
def test_opencv_sequence_of_the_tests_is_opencv_contribs_own(tmp_path):
    """The test sequence equals what opencv-contrib's GrayCodePattern generates (run in the
    benchmark's separate environment: opencv-contrib conflicts with the project's OpenCV)."""
    out = tmp_path / "cv.npz"
    code = ("import sys, numpy as np, cv2\n"
            "gc = cv2.structured_light.GrayCodePattern.create(100, 37)\n"
            "ok, pats = gc.generate()\n"
            "z = np.zeros((37, 100), np.uint8)\n"
            "black, white = gc.getImagesForShadowMasks(z.copy(), z.copy())\n"
            "np.savez(sys.argv[1], *pats, white, black)\n")
    subprocess.run([str(CONTRIB_PYTHON), "-c", code, str(out)], check=True)
    with np.load(out) as z:
        theirs = [z[f"arr_{i}"] for i in range(len(z.files))]
    ours = opencv_graycode.capture_sequence(100, 37)
    assert len(ours) == len(theirs) == 2 * (7 + 6) + 2
    for i, (a, b) in enumerate(zip(ours, theirs)):
        assert np.array_equal(a, b), f"image {i}"


def _sim_opencv_decode(tmp: Path, pm, factor: float) -> tuple[float, float, dict]:
    """OpenCV's capture sequence (columns, rows, white, black) shown by the simulated rig's
    projector on the metal cylinder, captured, written under cap_pattern.cpp's names and
    decoded through the shipped layout (projector size set to the sim projector's).

    Returns the share of lit pixels decoded within ±1 column of the truth — lit: the whole
    pixel footprint on the cylinder or the plate and lit by the projector (the ray trace) with
    the projector's light measurable, white − black at least the layout's shadow_threshold
    (3 % of full scale) — the same share of all the trace's lit pixels (those include a strip
    where the light grazes the cylinder's edge, a few DN above black), and the counts."""
    from dotshell_sim.bench import scale_profile

    raw = tomllib.loads((ROOT / "profiles" / "sim-metal-cylinder.toml").read_text())
    rig = connected_rig(scale_profile(raw, factor) if factor != 1 else raw)
    pw, ph = rig["projector"].resolution
    d = render_sequence(rig, opencv_graycode.capture_sequence(pw, ph), tmp / "caps",
                        opencv_graycode.file_name)
    column, _, traced = true_projector_coordinates(rig)
    layout = load_layout(_layout(tmp, (pw, ph)))
    seq = read_sequence(d, layout, pm)
    corr = seq.coding.decode(seq.frames, (pw, ph))
    correct = corr.valid & (np.abs(corr.column - column) <= 1.0)
    signal = seq.frames[0].astype(np.float64) - seq.frames[1]
    full_scale = 2 ** rig["camera"].bit_depth - 1
    lit = traced & (signal >= layout.decoder["shadow_threshold"] * full_scale)
    return float(correct[lit].mean()), float(correct[traced].mean()), corr.stats


def test_opencv_sequence_rendered_by_the_simulator_decodes(tmp_path, pm):
    share, share_traced, stats = _sim_opencv_decode(tmp_path, pm, 0.25)
    print(f"lit pixels within ±1 column: {100 * share:.2f} % ({100 * share_traced:.2f} % of all "
          "traced lit pixels)", stats)
    assert share >= 0.99 and share_traced >= 0.985


@pytest.mark.slow
def test_opencv_sequence_rendered_by_the_simulator_full_resolution(tmp_path, pm):
    share, share_traced, stats = _sim_opencv_decode(tmp_path, pm, 1.0)
    print(f"lit pixels within ±1 column: {100 * share:.2f} % ({100 * share_traced:.2f} % of all "
          "traced lit pixels)", stats)
    assert share >= 0.99 and share_traced >= 0.985  # measured 99.70 % (98.97 %)


def test_layout_frame_count_mismatch_names_the_files(tmp_path, pm):
    d, _ = _opencv_sequence(tmp_path)
    (d / "pattern_cam1_im22.png").unlink()
    with pytest.raises(RunError, match=r"expects 22 frames.*missing: pattern_cam1_im22.png"):
        layout = load_layout(_layout(tmp_path))
        coding = pm.create("coding", "graycode", layout.coding_settings())
        read_captures(d, layout, coding.frame_names(layout.projector_size))
    shutil.copy(d / "pattern_cam1_im1.png", d / "pattern_cam1_im22.png")
    shutil.copy(d / "pattern_cam1_im1.png", d / "pattern_cam1_im23.png")
    with pytest.raises(RunError, match="not in the layout: pattern_cam1_im23.png"):
        read_captures(d, layout, coding.frame_names(layout.projector_size))


def test_mismatched_frame_sizes_are_named(tmp_path, pm):
    d, _ = _opencv_sequence(tmp_path)
    cv2.imwrite(str(d / "pattern_cam1_im6.png"), np.zeros((10, 10), np.uint8))
    layout = load_layout(_layout(tmp_path))
    coding = pm.create("coding", "graycode", layout.coding_settings())
    with pytest.raises(RunError, match=r"frames differ in size.*pattern_cam1_im6.png \(10x10\)"):
        read_captures(d, layout, coding.frame_names(layout.projector_size))


def test_bad_layout_is_a_clear_error(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text('[layout]\nname = "x"\nfiles = "f.png"\nprojector_width = 8\n'
                 'projector_height = 8\norder = ["white", "black", "columns"]\n')
    with pytest.raises(RunError, match=r"needs an \{index\} field"):
        load_layout(p)
    with pytest.raises(RunError, match="shipped layouts: opencv-graycode, slstudio-graycode"):
        load_layout("no-such-layout")


@needs_skull
def test_slstudio_calibration_import_and_opencv_roundtrip(tmp_path):
    cal = read_opencv_calibration(SKULL / "calibration.xml")
    assert cal.camera.size == (1688, 1352) and cal.projector.size == (1824, 1140)
    assert cal.camera.K[0, 0] == pytest.approx(2195.12036, rel=1e-6)
    assert cal.projector.dist[0] == pytest.approx(-0.0314900056, rel=1e-6)
    assert cal.baseline_mm == pytest.approx(np.linalg.norm([-145.282562, -36.4983406, 67.9231644]),
                                            rel=1e-6)
    assert cal.rms["stereo"] == pytest.approx(0.421997, rel=1e-5)
    assert "placeholder" in cal.source
    for suffix in (".yml", ".xml"):
        back = read_opencv_calibration(write_opencv_calibration(cal, tmp_path / f"c{suffix}"))
        assert np.allclose(back.camera.K, cal.camera.K) and np.allclose(back.R, cal.R)
        assert np.allclose(back.projector.dist, cal.projector.dist)
        assert np.allclose(back.axis_point, cal.axis_point)


@needs_skull
def test_slstudio_skull_matches_slstudio_cloud(tmp_path, pm):
    res = reconstruct_captures(SKULL / "skull_gray", SKULL / "calibration.xml",
                               "slstudio-graycode", pm, tmp_path,
                               reference=SKULL / "skull_gray" / "pointCloud.mat")
    ref = res.report["reference"]
    print(ref)
    assert ref["reference_points"] == 93876
    assert ref["coverage_pct"] >= 95.0
    assert ref["to_reference_plane"]["median_mm"] <= 0.3
    assert ref["reference_to_points"]["median_mm"] <= 0.3
    assert (res.out_dir / "cloud.ply").stat().st_size > 1_000_000
    assert (res.out_dir / "previews" / "columns.png").is_file()


@needs_skull
def test_skull_errors_name_the_problem(tmp_path, pm, capsys):
    d = tmp_path / "caps"
    d.mkdir()
    for i in range(11):  # one frame short
        shutil.copy(SKULL / "skull_gray" / f"frameSeq_{i:02d}.bmp", d)
    code = main(["reconstruct", "--captures", str(d), "--calibration",
                 str(SKULL / "calibration.xml"), "--layout", "slstudio-graycode",
                 "--out", str(tmp_path)])
    msg = capsys.readouterr().err
    assert code == 2 and "expects 12 frames" in msg and "frameSeq_11.bmp" in msg
    shutil.copy(SKULL / "skull_gray" / "frameSeq_11.bmp", d)
    small = write_opencv_calibration(read_opencv_calibration(SKULL / "calibration.xml"),
                                     tmp_path / "c.yml")
    text = small.read_text().replace("frameWidth: 1688", "frameWidth: 1280")
    small.write_text(text)
    with pytest.raises(CalibrationError, match="frames are 1688x1352 px but the calibration"):
        reconstruct_captures(d, small, "slstudio-graycode", pm, tmp_path)
    code = main(["reconstruct", "--captures", str(d)])
    assert code == 2 and "missing: --calibration, --layout" in capsys.readouterr().err


def test_graycode_not_centred_carries_gray_of_the_column(pm):
    """`centred = false` (SLStudio, OpenCV): projector column c carries gray(c), MSB first."""
    coding = pm.create("coding", "graycode", {"axes": "columns", "inverse": False,
                                              "centred": False})
    pats = {p.name: p.image[0] for p in coding.patterns((100, 4))}
    c = np.arange(100)
    gray = c ^ (c >> 1)
    for i in range(7):
        assert np.array_equal(pats[f"col_{i:02d}"] > 0, ((gray >> (6 - i)) & 1) == 1)
