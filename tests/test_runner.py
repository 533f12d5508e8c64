"""Acquisition runner: abort keeps frames, device failures are retried or fail cleanly."""

import json
import subprocess
import sys
import threading

import numpy as np
import pytest

from conftest import ROOT, small_profile_dict, write_profile
from dotshell import hookimpl
from dotshell.backends import Backend
from dotshell.errors import DeviceError
from dotshell.events import EventBus, FrameCaptured
from dotshell.pipeline.commands import reconstruct_run
from dotshell.pipeline.scan import scan
from dotshell.plugins import PluginManager
from dotshell.profile.loader import load_profile
from dotshell.run.ply import read_ply
from dotshell.run.store import RunStore


class FlakyCameraPlugin:
    """A camera backend wrapping the simulator's that fails on chosen captures."""

    def __init__(self, fail_on: set[int]):
        self.fail_on = fail_on
        self.calls = 0

    @hookimpl
    def dotshell_cameras(self):
        from dotshell_sim.devices import CAMERA_SCHEMA, make_camera

        plugin = self

        class Flaky:
            def __init__(self, inner):
                self.inner = inner

            def __getattr__(self, name):
                return getattr(self.inner, name)

            resolution = property(lambda self: self.inner.resolution)
            bit_depth = property(lambda self: self.inner.bit_depth)

            def connect(self):
                self.inner.connect()

            def close(self):
                self.inner.close()

            def status(self):
                return self.inner.status()

            def ground_truth_calibration(self):  # capabilities are read from the class
                return self.inner.ground_truth_calibration()

            def capture(self):
                plugin.calls += 1
                if plugin.calls in plugin.fail_on:
                    raise DeviceError("frame timeout (USB)")
                return self.inner.capture()

        return [Backend("flaky-camera", lambda settings, context: Flaky(make_camera(
            settings=settings, context=context)), CAMERA_SCHEMA)]


def _pm(plugin=None):
    pm = PluginManager()
    pm.load_entry_points()
    if plugin:
        pm.register(plugin, name="flaky")
    return pm


def _profile(tmp_path, pm, views=3, backend="sim-camera"):
    raw = small_profile_dict(factor=0.2, views=views)
    raw["camera"]["backend"] = backend
    raw["camera"]["settings"]["supersample"] = 1
    raw["scan"]["acquisition"] = "show-capture"  # these tests fail and stop single captures
    raw["outputs"] = {"previews": False}
    return load_profile(write_profile(tmp_path / "p.toml", raw), pm)


def test_stop_midway_keeps_frames_marks_aborted_and_reconstructs_complete_views(tmp_path):
    pm = _pm()
    stop = threading.Event()
    bus = EventBus()
    seen = []

    def stop_in_view_1(ev):
        if isinstance(ev, FrameCaptured):
            seen.append(ev)
            if ev.view == 1 and ev.index == 5:
                stop.set()

    bus.subscribe(stop_in_view_1)
    result = scan(_profile(tmp_path, pm), pm, tmp_path / "runs", bus=bus, stop=stop)
    assert result.status == "aborted"
    manifest = json.loads((result.run_dir / "manifest.json").read_text())
    assert manifest["status"] == "aborted"
    assert [v["complete"] for v in manifest["views"]] == [True, False, False]
    assert manifest["views"][1]["frames"] == 6
    assert RunStore.open(result.run_dir).frames(1).count() == 6  # the stopped view's frames
    assert result.report["cloud"]["points"] > 0  # view 0 was processed
    again = reconstruct_run(result.run_dir, pm)
    assert [v["view"] for v in again.report["views"]] == [0]
    events = [json.loads(x)["event"] for x in (result.run_dir / "events.jsonl").read_text().splitlines()]
    assert "ScanFinished" in events and "view 2 of 3 has 6 of" in (result.run_dir / "events.jsonl").read_text()


def test_transient_device_error_is_retried(tmp_path):
    plugin = FlakyCameraPlugin(fail_on={3, 40})
    pm = _pm(plugin)
    msgs = []
    bus = EventBus()
    bus.subscribe(lambda ev: msgs.append(getattr(ev, "text", "")))
    result = scan(_profile(tmp_path, pm, views=2, backend="flaky-camera"), pm,
                  tmp_path / "runs", bus=bus)
    assert result.status == "completed"
    assert sum("frame timeout (USB) — retrying" in m for m in msgs) == 2
    assert result.report["validation"]["mean_rel_error_pct"] < 1.0


def test_persistent_device_error_fails_run_and_keeps_frames(tmp_path):
    plugin = FlakyCameraPlugin(fail_on=set(range(45, 60)))
    pm = _pm(plugin)
    with pytest.raises(DeviceError, match="view 1, frame .* failed 3 times; last error: frame timeout"):
        scan(_profile(tmp_path, pm, backend="flaky-camera"), pm, tmp_path / "runs")
    [run] = list((tmp_path / "runs").iterdir())
    manifest = json.loads((run / "manifest.json").read_text())
    assert manifest["status"] == "failed"
    assert manifest["views"][0]["complete"] and manifest["views"][1]["frames"] == 10
    store = RunStore.open(run)
    assert store.frames(0).count() == manifest["views"][0]["frames"]
    assert store.frames(1).count() == 10 and store.frames(2).count() == 0


def test_third_party_plugin_installed_with_pip_is_discovered_and_used(tmp_path, monkeypatch):
    site = tmp_path / "site"
    r = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps",
                        "--no-build-isolation", "--target", str(site),
                        str(ROOT / "plugins" / "examples" / "dotshell-xyz-export")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    monkeypatch.syspath_prepend(str(site))
    pm = _pm()
    info = pm.backends("exporter")["xyz-text"]
    assert info.plugin == "xyz" and info.distribution == "dotshell-xyz-export 1.0.0"
    raw = small_profile_dict(factor=0.2, views=2)
    raw["camera"]["settings"]["supersample"] = 1
    raw["outputs"] = {"previews": False}
    raw["export"] = {"xyz-text": {"delimiter": ",", "decimals": 5}}
    result = scan(load_profile(write_profile(tmp_path / "p.toml", raw), pm), pm, tmp_path / "runs")
    assert result.report["exports"] == {"xyz-text": ["cloud.xyz"]}
    xyz = np.loadtxt(result.run_dir / "cloud.xyz", delimiter=",")
    ply, _ = read_ply(result.run_dir / "cloud.ply")
    assert xyz.shape == ply.shape and np.allclose(xyz, ply, atol=1e-5)


def test_disk_write_failure_stops_scan_with_clear_error(tmp_path, monkeypatch):
    from dotshell.errors import RunError
    from dotshell.run.frames import TiffFrameStore

    real = TiffFrameStore.append
    count = {"n": 0}

    def failing(self, index, image):
        count["n"] += 1
        if count["n"] > 40:  # 34 frames a view: in the middle of view 1
            raise OSError(28, "No space left on device")
        return real(self, index, image)

    monkeypatch.setattr(TiffFrameStore, "append", failing)
    pm = _pm()
    with pytest.raises(RunError, match="could not write frame .* No space left on device"):
        scan(_profile(tmp_path, pm), pm, tmp_path / "runs")
    [run] = list((tmp_path / "runs").iterdir())
    store = RunStore.open(run)
    assert [store.frames(v).count() for v in range(3)] == [34, 6, 0]
    assert store.frames(1).read_one(5).shape == store.frames(0).read_one(0).shape  # readable
    assert json.loads((run / "manifest.json").read_text())["status"] == "failed"
