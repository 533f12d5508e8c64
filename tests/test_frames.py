"""Frame storage: TIFF stacks written as frames arrive, old PNG runs still read, PNG export."""

import json
import shutil

import cv2
import numpy as np
import pytest
import tifffile

from dotshell.cli.app import main
from dotshell.errors import FrameError, RunError
from dotshell.run.framecheck import FrameSpec
from dotshell.run.frames import PngFrameStore, TiffFrameStore, open_frames
from dotshell.pipeline.commands import reconstruct_run
from dotshell.plugins import PluginManager
from dotshell.run.ply import read_ply
from dotshell.run.store import RunStore

NAMES = ["white", "black", "col_00", "col_00_inv"]


def _frames(dtype=np.uint16, n=len(NAMES)):
    rng = np.random.default_rng(3)
    top = 4096 if dtype == np.uint16 else 256
    return rng.integers(0, top, (n, 9, 14), dtype=dtype)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_tiff_stack_roundtrips_and_reads_one_frame(tmp_path, dtype):
    frames = _frames(dtype)
    store = TiffFrameStore(tmp_path, 2, NAMES)
    for i, f in enumerate(frames):
        store.append(i, f)
    store.close()
    back = TiffFrameStore(tmp_path, 2, NAMES)
    assert back.path == tmp_path / "frames" / "view_002.tif" and back.count() == 4
    all_ = back.read_all()
    assert all_.dtype == dtype and np.array_equal(all_, frames)
    assert np.array_equal(back.read_one(3), frames[3])


def test_a_view_is_read_over_the_previous_views_array_and_still_checked(tmp_path):
    """`reconstruct` reads each view into the previous view's array (no fresh 110 MB array a
    view): the same frames as a fresh read; an array of another shape or a read-only one is
    not used; a value past the bit depth is refused either way, naming its frame."""
    views = [_frames(), _frames()[::-1].copy()]
    for v, frames in enumerate(views):
        store = TiffFrameStore(tmp_path, v, NAMES)
        for i, f in enumerate(frames):
            store.append(i, f)
        store.close()
    spec = FrameSpec(14, 9, 12)
    first = TiffFrameStore(tmp_path, 0, NAMES).read_all(spec)
    second = TiffFrameStore(tmp_path, 1, NAMES).read_all(spec, out=first)
    assert second is first and np.array_equal(second, views[1])
    assert TiffFrameStore(tmp_path, 0, NAMES).read_all(spec, out=first[:2]) is not first
    frozen = first.view()
    frozen.flags.writeable = False
    again = TiffFrameStore(tmp_path, 0, NAMES).read_all(spec, out=frozen)
    assert again is not frozen and np.array_equal(again, views[0])
    loud = views[0].copy()
    loud[2, 4, 5] = 4096  # 13 bit
    store = TiffFrameStore(tmp_path, 2, NAMES)
    for i, f in enumerate(loud):
        store.append(i, f)
    store.close()
    with pytest.raises(FrameError, match="frame 'col_00' .page 2. of .*holds values up to 4096"):
        TiffFrameStore(tmp_path, 2, NAMES).read_all(spec, out=first)


def test_frames_of_a_view_cut_short_stay_readable(tmp_path):
    """A crash mid-view (the writer never closed) leaves every appended frame readable."""
    frames = _frames()
    writing = TiffFrameStore(tmp_path, 0, NAMES)
    for i in range(3):
        writing.append(i, frames[i])
    reader = TiffFrameStore(tmp_path, 0, NAMES)
    assert reader.count() == 3
    assert np.array_equal(reader.read_one(2), frames[2])
    with pytest.raises(RunError, match=r"frame 3 \('col_00_inv'\) of view 0 is missing"):
        reader.read_all()
    writing.close()


@pytest.mark.parametrize("byteorder,bigtiff", [("<", False), (">", False), (">", True)])
def test_page_reader_reads_any_uncompressed_stack_and_stops_where_a_file_is_cut(
        tmp_path, byteorder, bigtiff):
    """dotshell.run.tiffpages against tifffile as the independent writer: either byte order,
    classic or BigTIFF, several strips per page; a file cut inside a page keeps the pages
    before it; compressed pages are refused."""
    frames = _frames()
    path = tmp_path / "frames" / "view_000.tif"
    path.parent.mkdir()
    with tifffile.TiffWriter(path, byteorder=byteorder, bigtiff=bigtiff) as tw:
        for name, f in zip(NAMES, frames):
            tw.write(f, metadata=None, description=name, rowsperstrip=4)
    store = TiffFrameStore(tmp_path, 0, NAMES)
    back = store.read_all()
    assert back.dtype == np.uint16 and back.dtype.isnative and np.array_equal(back, frames)
    data = path.read_bytes()
    last_page = data.rfind(frames[3].astype(np.dtype(np.uint16).newbyteorder(byteorder))
                           .tobytes()[:64])
    path.write_bytes(data[:last_page + 100])
    assert store.count() == 3 and np.array_equal(store.read_one(2), frames[2])
    tifffile.imwrite(path, frames[0], compression="zlib", metadata=None, description="white")
    with pytest.raises(RunError, match="page 0 is not an uncompressed 8/16-bit"):
        store.read_one(0)


def test_a_page_linked_before_its_directory_is_written_is_not_yet_there(tmp_path):
    """A reader of a view being written can find the next page linked while its directory is
    still zeros: the stack then holds the pages before it (it was read as a damaged page)."""
    frames = _frames()
    path = tmp_path / "frames" / "view_000.tif"
    path.parent.mkdir()
    with tifffile.TiffWriter(path) as tw:
        for name, f in zip(NAMES, frames):
            tw.write(f, metadata=None, description=name)
    with tifffile.TiffFile(path) as tf:
        last = tf.pages[3].offset
    data = bytearray(path.read_bytes())
    data[last:last + 2 + 12 * 12] = bytes(2 + 12 * 12)  # its entry count and entries
    path.write_bytes(bytes(data))
    store = TiffFrameStore(tmp_path, 0, NAMES)
    assert store.count() == 3 and np.array_equal(store.read_one(2), frames[2])


def test_frame_store_refuses_bad_input_with_clear_errors(tmp_path):
    store = TiffFrameStore(tmp_path, 0, NAMES)
    with pytest.raises(RunError, match="frame 1 .'black'. arrived after 0 frames"):
        store.append(1, _frames()[0])
    with pytest.raises(RunError, match="no frame 4"):
        store.append(4, _frames()[0])
    store.append(0, _frames()[0])
    store.close()
    with pytest.raises(RunError, match="page 0 holds frame 'white' where the run's sequence has "
                                       "'dark'"):
        TiffFrameStore(tmp_path, 0, ["dark"]).read_one(0)
    (tmp_path / "frames" / "view_001.tif").write_bytes(b"")  # created, nothing written yet
    assert TiffFrameStore(tmp_path, 1, NAMES).count() == 0
    (tmp_path / "frames" / "view_001.tif").write_bytes(b"not a tiff")
    with pytest.raises(RunError, match="view_001.tif is not a readable frame stack"):
        TiffFrameStore(tmp_path, 1, NAMES).read_all()
    with pytest.raises(RunError, match="'zarr/9', which this dotshell cannot read"):
        open_frames(tmp_path, 0, {"frame_format": "zarr/9", "frame_names": NAMES})
    with pytest.raises(RunError, match="read-only"):
        PngFrameStore(tmp_path, 0, NAMES).append(0, _frames()[0])


def test_old_png_runs_reconstruct_and_frames_export_as_png(small_scan, tmp_path, capsys):
    """`dotshell frames RUN --png` writes the PNG layout of runs before TIFF stacks; such a run
    (no frame_format in its manifest) reconstructs to the same cloud."""
    result, _ = small_scan
    run = tmp_path / "run"
    shutil.copytree(result.run_dir, run, symlinks=True)
    assert main(["frames", str(run)]) == 0
    listing = capsys.readouterr().out
    assert "tiff-stack/1, 34 per view" in listing and "view_005.tif" in listing
    assert main(["frames", str(run), "--png", str(run / "frames")]) == 0
    assert "204 frames of 6 view(s)" in capsys.readouterr().out
    store = RunStore.open(run)
    tiff = store.read_frames(3)
    png = cv2.imread(str(run / "frames" / "view_003" / "005_col_01_inv.png"), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint16 and np.array_equal(png, tiff[5])
    for tif in (run / "frames").glob("*.tif"):
        tif.unlink()
    manifest = json.loads((run / "manifest.json").read_text())
    del manifest["frame_format"]
    (run / "manifest.json").write_text(json.dumps(manifest))
    assert isinstance(store.frames(3), PngFrameStore)
    assert np.array_equal(store.read_frames(3), tiff)
    pm = PluginManager()
    pm.load_entry_points()
    reconstruct_run(run, pm)
    before, _ = read_ply(result.run_dir / "cloud.ply")
    after, _ = read_ply(run / "cloud.ply")
    assert len(after) == len(before) and np.allclose(after, before, atol=1e-6)
    assert main(["frames", str(run), "--view", "9"]) == 2
    assert "there is no view 9" in capsys.readouterr().err


def test_a_view_is_synced_once_before_it_is_reported_captured(tmp_path, monkeypatch):
    """The frame writer fsyncs each view's stack once (file and directory), after its last
    frame and before ViewCaptured; not once per frame."""
    import os

    from conftest import write_test_profile
    from dotshell.events import EventBus, FrameCaptured, ViewCaptured
    from dotshell.pipeline.scan import scan
    from dotshell.profile.loader import load_profile

    log = []
    real_fsync = os.fsync

    def fsync(fd):
        log.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        return real_fsync(fd)

    monkeypatch.setattr("dotshell.run.frames.os.fsync", fsync)
    bus = EventBus()
    bus.subscribe(lambda ev: log.append(("frame", ev.view)) if isinstance(ev, FrameCaptured)
                  else log.append(("captured", ev.view)) if isinstance(ev, ViewCaptured)
                  else None)
    pm = PluginManager()
    pm.load_entry_points()
    result = scan(load_profile(write_test_profile(tmp_path), pm), pm, tmp_path / "runs", bus=bus)
    frames_dir = str(result.run_dir / "frames")
    per_view = len(RunStore.open(result.run_dir).manifest["frame_names"])
    for view in (0, 1):
        syncs = [i for i, e in enumerate(log) if e == ("fsync", f"{frames_dir}/view_{view:03d}.tif")]
        frames = [i for i, e in enumerate(log) if e == ("frame", view)]
        captured = log.index(("captured", view))
        assert len(frames) == per_view and len(syncs) == 1  # once per view, not per frame
        assert log[syncs[0] + 1] == ("fsync", frames_dir)  # and its directory entry
        assert frames[-1] < syncs[0] < syncs[0] + 1 < captured
