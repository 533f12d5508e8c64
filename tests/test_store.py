import numpy as np
import pytest

from dotshell.errors import RunError
from dotshell.run.ply import read_ply, write_ply
from dotshell.run.store import RunStore


def test_frames_roundtrip_losslessly_and_manifest_tracks_views(tmp_path):
    store = RunStore.create(tmp_path, "my profile/x")
    assert store.root.parent == tmp_path and "my-profile-x" in store.root.name
    store.init_manifest("p", [0.0, 180.0], ["white", "black"])
    rng = np.random.default_rng(0)
    f16 = rng.integers(0, 4096, (12, 17), dtype=np.uint16)
    frames = store.frames(1)
    frames.append(0, f16)
    frames.append(1, f16 // 3)
    frames.close()
    store.mark_view(1, 2, True)
    back = store.read_frames(1)
    assert back.dtype == np.uint16 and back.shape == (2, 12, 17)
    assert np.array_equal(back[0], f16) and np.array_equal(back[1], f16 // 3)
    m = RunStore.open(store.root).manifest
    assert m["views"][1] == {"index": 1, "angle_deg": 180.0, "frames": 2, "complete": True}
    assert "numpy" in m["versions"] and m["status"] == "running"
    assert m["frame_format"] == "tiff-stack/1"
    assert not list(store.root.rglob("*.tmp"))


def test_events_are_appended_per_event(tmp_path):
    store = RunStore.create(tmp_path, "p")
    store.append_event({"event": "A", "n": 1})
    # readable before close: flushed per event
    assert (store.root / "events.jsonl").read_text().count("\n") == 1
    store.append_event({"event": "B", "n": np.int64(2)})
    store.close()
    assert [e["event"] for e in store.events()] == ["A", "B"]


def test_missing_frame_and_non_run_are_clear_errors(tmp_path):
    with pytest.raises(RunError, match="not a dotshell run directory"):
        RunStore.open(tmp_path)
    store = RunStore.create(tmp_path, "p")
    store.init_manifest("p", [0.0], ["white"])
    with pytest.raises(RunError, match="the frame stack of view 0 is missing"):
        store.read_frames(0)
    with pytest.raises(RunError, match="2-D uint8 or uint16"):
        store.frames(0).append(0, np.zeros((4, 4), np.float32))


def test_ply_roundtrip(tmp_path):
    pts = np.random.default_rng(1).normal(size=(100, 3)) * 10
    write_ply(tmp_path / "c.ply", pts, view=np.arange(100) % 7)
    back, sc = read_ply(tmp_path / "c.ply")
    assert np.allclose(back, pts, atol=1e-5) and np.array_equal(sc["view"], np.arange(100) % 7)
