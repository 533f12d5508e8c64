"""Captures from other rigs: layout files, frame ordering and polarity, SLStudio's calibration
import and its real skull capture (shared/data/slstudio-skull) against SLStudio's own cloud."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import ROOT
from dotshell.cli import main
from dotshell.errors import CalibrationError, RunError
from dotshell.geometry.opencv_io import read_opencv_calibration, write_opencv_calibration
from dotshell.pipeline.captures import (capture_order, load_layout, read_captures,
                                        reconstruct_captures, to_coding_frames)
from dotshell.plugins import PluginManager

SKULL = ROOT.parent / "shared" / "data" / "slstudio-skull"
needs_skull = pytest.mark.skipif(not (SKULL / "skull_gray").is_dir(),
                                 reason="shared/data/slstudio-skull is not present")


@pytest.fixture
def pm():
    m = PluginManager()
    m.load_entry_points()
    return m


def _opencv_sequence(tmp: Path, proj=(64, 16), cam=(200, 40)) -> tuple[Path, np.ndarray]:
    """Frames as OpenCV's GrayCodePattern defines them, written independently of dotshell's
    coder: column c carries gray(c) (not centred); the first image of each pair is lit where
    the gray bit is 0; columns then rows, MSB first; then white, black. The camera sees the
    projector stretched: projector column = (x + 0.5) * proj_w / cam_w - 0.5."""
    pw, ph = proj
    cw, ch = cam
    cols = np.floor((np.arange(cw) + 0.5) * pw / cw).astype(int)
    rows = np.floor((np.arange(ch) + 0.5) * ph / ch).astype(int)
    frames = []
    for values, n, axis in ((cols, int(np.ceil(np.log2(pw))), 1), (rows, int(np.ceil(np.log2(ph))), 0)):
        gray = values ^ (values >> 1)
        for k in range(n - 1, -1, -1):
            bit = (gray >> k) & 1
            lit = (bit == 0).astype(np.uint8) * 200 + 20
            img = np.broadcast_to(lit[None, :] if axis == 1 else lit[:, None], (ch, cw))
            frames += [img, 240 - img]
    frames += [np.full((ch, cw), 220, np.uint8), np.full((ch, cw), 20, np.uint8)]
    d = tmp / "caps"
    d.mkdir()
    for i, f in enumerate(frames):
        cv2.imwrite(str(d / f"pattern_{i:02d}.png"), np.ascontiguousarray(f))
    truth = (np.arange(cw) + 0.5) * pw / cw - 0.5
    return d, truth


def _layout(tmp: Path, proj=(64, 16)) -> Path:
    text = (ROOT / "layouts" / "opencv-graycode.toml").read_text()
    text = text.replace("projector_width = 1024", f"projector_width = {proj[0]}")
    text = text.replace("projector_height = 768", f"projector_height = {proj[1]}")
    p = tmp / "opencv.toml"
    p.write_text(text)
    return p


def test_opencv_layout_decodes_the_opencv_sequence(tmp_path, pm):
    d, truth = _opencv_sequence(tmp_path)
    layout = load_layout(_layout(tmp_path))
    coding = pm.create("coding", "graycode", layout.coding_settings())
    names = coding.frame_names(layout.projector_size)
    order = capture_order(layout, names)
    assert order[:2] == ["col_00_inv", "col_00"] or order[:2] == ["col_00", "col_00_inv"]
    assert order[-2:] == ["white", "black"] and len(order) == 2 + 2 * (6 + 4)
    frames = to_coding_frames(read_captures(d, layout, names), layout, names)
    corr = coding.decode(frames, layout.projector_size)
    assert corr.valid.mean() > 0.9
    err = np.abs(corr.column - truth[None, :])[corr.valid]
    assert np.median(err) < 0.3 and err.max() < 1.0  # right order, polarity and code offset
    wrong = load_layout(_layout(tmp_path))  # same frames read with the opposite polarity
    object.__setattr__(wrong, "bright_is_one", True)
    bad = coding.decode(to_coding_frames(read_captures(d, wrong, names), wrong, names),
                        layout.projector_size)
    assert np.nanmedian(np.abs(bad.column - truth[None, :])[bad.valid]) > 5


def test_layout_frame_count_mismatch_names_the_files(tmp_path, pm):
    d, _ = _opencv_sequence(tmp_path)
    (d / "pattern_21.png").unlink()
    with pytest.raises(RunError, match=r"expects 22 frames.*missing: pattern_21.png"):
        layout = load_layout(_layout(tmp_path))
        coding = pm.create("coding", "graycode", layout.coding_settings())
        read_captures(d, layout, coding.frame_names(layout.projector_size))
    shutil.copy(d / "pattern_00.png", d / "pattern_21.png")
    shutil.copy(d / "pattern_00.png", d / "pattern_22.png")
    with pytest.raises(RunError, match="not in the layout: pattern_22.png"):
        read_captures(d, layout, coding.frame_names(layout.projector_size))


def test_mismatched_frame_sizes_are_named(tmp_path, pm):
    d, _ = _opencv_sequence(tmp_path)
    cv2.imwrite(str(d / "pattern_05.png"), np.zeros((10, 10), np.uint8))
    layout = load_layout(_layout(tmp_path))
    coding = pm.create("coding", "graycode", layout.coding_settings())
    with pytest.raises(RunError, match=r"frames differ in size.*pattern_05.png \(10x10\)"):
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
