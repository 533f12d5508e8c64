"""The two acquisition engines behind one protocol (dotshell/pipeline/engines.py): chosen from
``[scan] acquisition`` and the devices' capabilities, they take the same frames of the same
shots on the simulator."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import small_profile_dict, write_profile
from dotshell.coding import PatternFrame
from dotshell.errors import ProfileError
from dotshell.events import EventBus
from dotshell.pipeline.engines import ShowCaptureEngine, choose_engine
from dotshell.pipeline.pdi import plan_shots
from dotshell.pipeline.sequenced import SequencedCapture
from dotshell.profile.loader import load_profile
from dotshell.rig.assembly import Rig


def _profile(tmp_path, pm):
    raw = small_profile_dict(factor=0.12, views=2)
    raw["camera"]["settings"].update(supersample=1)
    raw["outputs"] = {"previews": False}
    return load_profile(write_profile(tmp_path / "p.toml", raw), pm)


def _patterns(width: int, height: int) -> list[PatternFrame]:
    white = np.full((height, width), 255, np.uint8)
    left = white.copy()
    left[:, width // 2:] = 0
    return [PatternFrame("white", white), PatternFrame("black", np.zeros_like(white)),
            PatternFrame("left", left)]


def _take(rig, patterns, mode: str, tries: list[str]):
    scan = {**rig.profile.data["scan"], "acquisition": mode}
    shots = plan_shots(patterns, scan)

    def retry(action, what):
        tries.append(what)
        return action()

    engine = choose_engine(rig, patterns, shots, scan, EventBus(), retry)
    held = []
    frames = []
    for i in range(len(shots)):
        frame, info = engine.frame(0, i)
        held.append(engine.holds_frames())
        frames.append((np.asarray(frame, float), info))
    return engine, frames, held


def test_both_engines_take_the_same_frames_behind_one_protocol(tmp_path, pm):
    with Rig(_profile(tmp_path, pm), pm) as rig:
        rig.stage.move_to(0.0)
        rig.camera.set_exposure(rig.profile.data["scan"]["exposure_ms"])
        patterns = _patterns(*rig.projector.resolution)
        tries: dict[str, list[str]] = {"show-capture": [], "auto": []}
        shown, by_show, held_show = _take(rig, patterns, "show-capture", tries["show-capture"])
        auto, by_seq, held_seq = _take(rig, patterns, "auto", tries["auto"])
    assert isinstance(shown, ShowCaptureEngine) and shown.name == "show-capture"
    # the simulator's projector stores sequences and its camera takes a trigger
    assert isinstance(auto, SequencedCapture) and auto.name == "sequenced"
    # show-capture: one retried step per frame, nothing held back; sequenced: one run of three
    # patterns, the two frames not yet handed over held (a stop must not drop them)
    assert tries["show-capture"] == ["view 0, frame 'white'", "view 0, frame 'black'",
                                     "view 0, frame 'left'"]
    assert tries["auto"] == ["view 0, sequence of 3 patterns"]
    assert held_show == [False] * 3 and held_seq == [True, True, False]
    assert all(info is not None for _, info in by_seq)
    white, black, left = (f for f, _ in by_seq)
    scale = float(np.median(white))
    for (a, _), (b, _) in zip(by_show, by_seq):  # the same image within the sensor noise
        assert np.median(np.abs(a - b)) < 0.1 * scale
    for i in (0, 2):  # the lit patterns: the same picture (the dark one is noise only)
        assert np.corrcoef(by_show[i][0].ravel(), by_seq[i][0].ravel())[0, 1] > 0.99
    lit = white > black + 0.5 * (white.max() - black.max())
    assert lit.sum() > 100
    # the half-lit pattern: about half the lit pixels stay lit, in both engines
    for frames in (by_show, by_seq):
        share = np.mean(frames[2][0][lit] > (frames[0][0][lit] + frames[1][0][lit]) / 2)
        assert 0.2 < share < 0.8


def test_sequenced_asked_of_a_rig_that_cannot_is_refused_by_the_chooser(tmp_path, pm):
    raw = _profile(tmp_path, pm).raw()
    raw["camera"] = {"backend": "opencv", "settings": {"source": str(tmp_path / "none.mkv")}}
    raw["calibration"] = {"source": "file", "file": "cal.json"}
    prof = load_profile(write_profile(tmp_path / "cv.toml", raw), pm)
    rig = Rig(prof, pm)
    scan = {**prof.data["scan"], "acquisition": "sequenced"}
    patterns = _patterns(*rig.projector.resolution)
    with pytest.raises(ProfileError, match="the camera \\(opencv\\) lacks arm"):
        choose_engine(rig, patterns, plan_shots(patterns, scan), scan, EventBus(),
                      lambda action, what: action())
    scan["acquisition"] = "auto"
    engine = choose_engine(rig, patterns, plan_shots(patterns, scan), scan, EventBus(),
                           lambda action, what: action())
    assert engine.name == "show-capture"
