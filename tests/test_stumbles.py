"""Messages that save a new user's time (issue 27's stumbles): each names the thing to change."""

from __future__ import annotations

from dotshell.cli.app import main
from dotshell.cli.decode import loss_notes


def test_layout_files_matching_nothing_points_at_files_and_first_index(tmp_path, capsys):
    (tmp_path / "img_001.png").write_bytes(b"")
    assert main(["decode", "--captures", str(tmp_path), "--layout", "opencv-graycode",
                 "--out", str(tmp_path / "out")]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "no file matches the files = 'pattern_cam1_im{index}.png'" in err
    assert "first_index = 1" in err and "holds img_001.png" in err
    assert "Set [layout] files (and first_index" in err and "order, inverse" not in err


def test_set_layout_key_says_to_copy_the_layout(tmp_path, capsys):
    assert main(["calibrate", "--captures", str(tmp_path), "--layout", "opencv-graycode",
                 "--board", "10x8", "--square", "23.2", "--set",
                 "layout.projector_width=800"]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "--set layout.projector_width=…" in err
    assert "opencv-graycode.toml my-layout.toml" in err and "--layout my-layout.toml" in err


def test_loss_lines_name_their_meaning_and_fix():
    counts = {"pixels": 1000, "decoded": 600, "shadow": 20, "uncertain": 270,
              "row_rejected": 3}
    notes = loss_notes(counts)
    assert len(notes) == 2  # shadow is 2 %: no note; row rejections always explained
    assert notes[0].startswith("uncertain (27.0 %)") and 'classification = "adaptive"' in notes[0]
    assert "[decoder]" in notes[0]
    assert notes[1].startswith("row rejected (0.3 %)")
    assert "do not meet in one point" in notes[1] and "calibration" in notes[1]


def test_opencv_layout_says_what_min_contrast_does():
    """The shipped opencv-graycode layout names its classification, and min_contrast's help
    says what it does under each (it guards only the finest pairs under robust and adaptive)."""
    from dotshell_codings.graycode import SETTINGS_SCHEMA

    from dotshell.run.capture_layouts import load_layout

    layout = load_layout("opencv-graycode")
    assert layout.coding_settings()["classification"] == "adaptive"
    text = SETTINGS_SCHEMA["min_contrast"].help
    assert "contrast classification" in text and "robust and adaptive" in text
