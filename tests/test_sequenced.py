"""The simulator's time model, the sequenced acquisition path and the pre-scan rig checks
(``dotshell check --connect --latency``)."""

from __future__ import annotations

import subprocess
import sys
import time

import numpy as np
import pytest

from conftest import small_profile_dict, write_profile, write_test_profile
from dotshell.run.store import RunStore
from dotshell.devices import SequencePattern
from dotshell.errors import CalibrationError, DeviceTimeout, ProfileError
from dotshell.events import EventBus
from dotshell.geometry.calibration import RigCalibration
from dotshell.pipeline.scan import scan
from dotshell.pipeline.sequenced import pattern_period_ms, plan_runs
from dotshell.pipeline.pdi import Shot
from dotshell.profile.loader import load_profile
from dotshell.rig.assembly import Rig
from dotshell.rig.checks import check_resolutions, measure_latency


def _rig(tmp_path, pm, camera=None, projector=None, **scan_keys):
    raw = small_profile_dict(factor=0.12, views=2)
    raw["camera"]["settings"].update(supersample=1, **(camera or {}))
    raw["projector"]["settings"].update(projector or {})
    raw["scan"].update(scan_keys)
    raw["outputs"] = {"previews": False}
    return load_profile(write_profile(tmp_path / "p.toml", raw), pm)


def test_a_capture_before_the_display_settled_sees_a_blend(tmp_path, pm):
    prof = _rig(tmp_path, pm, camera={"readout_ms": 10.0},
                projector={"display_latency_ms": 30.0})
    with Rig(prof, pm) as rig:
        cam, proj = rig.camera, rig.projector
        w, h = proj.resolution
        proj.show(np.full((h, w), 255, np.uint8))
        time.sleep(0.5)
        white = cam.expected_electrons()
        clock = cam.world.clock
        t0 = clock.now()
        proj.show(np.zeros((h, w), np.uint8))
        t_black = proj.timeline.segments[-1].start_s   # when the panel turns black
        assert t_black - t0 >= 0.030
        early = cam.expected_electrons(t_black - 0.025)  # 20 ms exposure ending before: white
        mixed = cam.expected_electrons(t_black - 0.010)  # half of it white, half black
        late = cam.expected_electrons(t_black)
        lit = white > 4 * late + 100
        ratio = (mixed[lit] - late[lit]) / (white[lit] - late[lit])
        assert np.allclose(early[lit], white[lit])
        assert np.median(ratio) == pytest.approx(0.5, abs=0.02)
        cam.capture()
        assert clock.now() - t0 >= 0.030  # exposure + readout passed on the sim clock


def test_triggered_frames_follow_the_projector_and_missed_edges_time_out(tmp_path, pm):
    prof = _rig(tmp_path, pm, camera={"readout_ms": 30.0, "overlap_readout": False})
    with Rig(prof, pm) as rig:
        cam, proj = rig.camera, rig.projector
        w, h = proj.resolution
        seq = [SequencePattern(np.full((h, w), v, np.uint8), f"v{v}", i)
               for i, v in enumerate((0, 255, 0))]
        assert cam.min_trigger_period_ms(20.0) == 50.0
        cam.arm(3, 20.0)
        with pytest.raises(DeviceTimeout, match="0 of 3 .* wired"):
            cam.read_armed(0.2)  # armed, but the sequence never started
        proj.load_sequence(seq, 20.0, 50.0)
        cam.arm(3, 20.0)
        proj.start_sequence()
        got = cam.read_armed(1.0)
        means = [f.mean() for f, _ in got]
        assert means[1] > 10 * means[0] and means[2] < means[1] / 10
        assert got[1][1].timestamp_s - got[0][1].timestamp_s == pytest.approx(0.05)
        proj.load_sequence(seq, 20.0, 20.0)  # faster than the camera reads out
        cam.arm(3, 20.0)
        proj.start_sequence()
        with pytest.raises(DeviceTimeout, match="trigger edges came faster than the camera's "
                                                "50.00 ms minimum period"):
            cam.read_armed(0.5)


def test_period_choice_and_runs():
    class Proj:
        def shortest_period_ms(self, exposure_ms, at_least_ms):
            return max(exposure_ms, at_least_ms)

    class Cam:
        def min_trigger_period_ms(self, exposure_ms):
            return exposure_ms + 16.0

    assert pattern_period_ms(Proj(), Cam(), 20.0) == 36.0
    assert pattern_period_ms(Proj(), Cam(), 20.0, 40.0) == 40.0
    with pytest.raises(ProfileError, match="camera would miss triggers"):
        pattern_period_ms(Proj(), Cam(), 20.0, 30.0)
    shots = [Shot("a.par", 0, 0.0), Shot("b.par", 1, 0.0), Shot("a.perp", 0, 90.0)]
    assert [(r.analyzer_deg, r.shots) for r in plan_runs(shots)] == [(0.0, (0, 1)),
                                                                    (90.0, (2,))]


def test_sequenced_pdi_scan_takes_two_runs_per_view(tmp_path, pm):
    prof = _rig(tmp_path, pm, acquisition="sequenced", pdi=True)
    raw_an = {"backend": "sim-analyzer", "settings": {}}
    prof = load_profile(write_profile(tmp_path / "pdi.toml", {**prof.raw(), "analyzer": raw_an}),
                        pm)
    result = scan(prof, pm, tmp_path / "runs", bus=EventBus())
    assert result.status == "completed"
    store = RunStore.open(result.run_dir)
    names = store.manifest["frame_names"][:store.frames(0).count()]
    perp = sum(n.endswith(".perp") for n in names)
    par = sum(n.endswith(".par") for n in names)
    assert perp == par > 20 and result.report["validation"]["mean_rel_error_pct"] < 1.0


def test_sequenced_asked_of_devices_that_cannot(tmp_path, pm):
    prof = _rig(tmp_path, pm, acquisition="sequenced")
    raw = {**prof.raw()}
    raw["camera"] = {"backend": "opencv", "settings": {"source": str(tmp_path / "none.mkv")}}
    raw["calibration"] = {"source": "file", "file": "cal.json"}
    prof = load_profile(write_profile(tmp_path / "cv.toml", raw), pm)
    from dotshell.pipeline.sequenced import uses_sequenced

    rig = Rig(prof, pm)
    with pytest.raises(ProfileError, match="the camera \\(opencv\\) lacks arm"):
        uses_sequenced(rig, prof.data["scan"])


def test_resolution_mismatch_is_caught_before_a_scan(tmp_path, pm):
    prof = _rig(tmp_path, pm)
    with Rig(prof, pm) as rig:
        calib = rig.calibration()
        check_resolutions(rig, calib, "p.toml")  # the truth matches
        wrong = RigCalibration(camera=calib.camera.scaled(2.0), projector=calib.projector,
                               R=calib.R, T=calib.T, axis_point=calib.axis_point,
                               axis_direction=calib.axis_direction)
        with pytest.raises(CalibrationError, match="the camera gives 154x123 px but the "
                                                   "calibration's camera is 308x246 px"):
            check_resolutions(rig, wrong, "p.toml")


def test_check_latency_prints_a_settle_ms_covering_the_display(tmp_path):
    path = write_test_profile(tmp_path)
    import tomllib

    raw = tomllib.loads(path.read_text())
    raw["projector"]["settings"].update(display_latency_ms=40.0, refresh_hz=60.0)
    raw["camera"]["settings"]["readout_ms"] = 10.0
    write_profile(path, raw)
    r = subprocess.run([sys.executable, "-m", "dotshell.cli.app", "check", str(path), "--connect",
                        "--latency"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    settle = float(r.stdout.split("settle_ms = ")[1].split()[0])
    seen = float(r.stdout.split("full pattern is seen ")[1].split()[0])
    assert 40.0 <= seen <= 40.0 + 1000 / 60 + 2 and seen * 1.25 <= settle <= seen * 1.25 + 5


def test_sequenced_trigger_timeouts_are_retried_then_named(tmp_path, pm, monkeypatch):
    from dotshell.errors import DeviceError
    from dotshell_sim.devices import SimCamera

    real = SimCamera.read_armed
    failures = {"left": 1}

    def flaky(self, timeout_s):
        if failures["left"] > 0:
            failures["left"] -= 1
            raise DeviceTimeout("sim-camera: 3 of 30 triggered frames arrived")
        return real(self, timeout_s)

    monkeypatch.setattr(SimCamera, "read_armed", flaky)
    messages = []
    bus = EventBus()
    bus.subscribe(lambda ev: messages.append(getattr(ev, "text", "")))
    result = scan(_rig(tmp_path, pm, acquisition="sequenced"), pm, tmp_path / "ok", bus=bus)
    assert result.status == "completed"
    retried = [m for m in messages if "retrying" in m]
    assert len(retried) == 1 and retried[0].startswith("view 0, sequence of ")
    assert "3 of 30 triggered frames" in (result.run_dir / "events.jsonl").read_text()
    failures["left"] = 99
    with pytest.raises(DeviceError, match="view 0, sequence of .* failed 3 times; last error: "
                                          "sim-camera: 3 of 30"):
        scan(_rig(tmp_path, pm, acquisition="sequenced"), pm, tmp_path / "fail", bus=EventBus())
