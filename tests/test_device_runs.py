"""Scans on mixed rigs: a real stage driver on its protocol emulator with the simulated camera
and projector. Accuracy as on the all-simulated rig; abort and Ctrl-C stop a move within 0.5 s;
an unplugged stage is reconnected (or the run fails cleanly); plugin faults, retries, device
log lines, identity, read-back angles and frame metadata end up in the run."""

import json
import os
import signal
import subprocess
import sys
import threading
import time
import tomllib

import numpy as np
import pytest

from conftest import ROOT, small_profile_dict, write_profile
from dotshell import hookimpl
from dotshell.backends import Backend
from dotshell.cli.app import main
from dotshell.devices import FrameInfo
from dotshell.errors import DeviceLostError
from dotshell.events import EventBus
from dotshell.pipeline.scan import scan
from dotshell.plugins import PluginManager
from dotshell.profile.loader import load_profile
from dotshell.run.store import RunStore
from dotshell_sim.bench import scale_profile

BACKEND = {"grbl": "grbl", "zaber": "zaber", "apt": "thorlabs-apt"}


#: the scale of the scans whose accuracy is checked (measured, 4 views, every backend and the
#: all-sim rig alike: mean 0.157 %, sd 0.311 % against the bounds' 0.5 %, radius 7.6966 mm,
#: coverage 99.9 %), and of those that only need a scan to run (stops, signals, reconnects,
#: faults: 160x128 px; the scan's time is mostly the simulator's)
ACCURACY_SCALE = 0.15
TINY_SCALE = 0.125


def emu_profile(tmp_path, emulator, port, views=4, factor=TINY_SCALE, **scan):
    """profiles/emu-<emulator>-metal-cylinder.toml at ``factor`` scale, 1 ray per pixel."""
    raw = tomllib.loads((ROOT / "profiles" / f"emu-{emulator}-metal-cylinder.toml").read_text())
    raw = scale_profile(raw, factor)
    raw["camera"]["settings"]["supersample"] = 1
    raw["stage"]["settings"]["port"] = str(port)
    raw["scan"].update(views=views, **scan)
    raw["outputs"] = {"previews": False}
    return write_profile(tmp_path / f"emu-{emulator}.toml", raw)


@pytest.fixture(scope="module")
def all_sim_report(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("allsim")
    raw = small_profile_dict(ACCURACY_SCALE, 4)
    raw["camera"]["settings"]["supersample"] = 1
    raw["outputs"] = {"previews": False}
    pm = PluginManager()
    pm.load_entry_points()
    return scan(load_profile(write_profile(tmp / "p.toml", raw), pm), pm, tmp / "runs").report


def events(run_dir):
    return [json.loads(line) for line in (run_dir / "events.jsonl").read_text().splitlines()]


def manifest(run_dir):
    return json.loads((run_dir / "manifest.json").read_text())


@pytest.mark.parametrize("emulator", ["grbl", "zaber", "apt"])
def test_full_scan_with_each_real_stage_backend_meets_the_simulated_rig_bounds(
        tmp_path, dotshell_pm, serial_emulator, all_sim_report, emulator):
    emu = serial_emulator(emulator, speed_deg_s=720.0)
    profile = load_profile(emu_profile(tmp_path, emulator, emu.port, factor=ACCURACY_SCALE),
                           dotshell_pm)
    result = scan(profile, dotshell_pm, tmp_path / "runs")
    v, ref = result.report["validation"], all_sim_report["validation"]
    assert result.status == "completed"
    assert v["mean_rel_error_pct"] < 0.5 and v["std_rel_error_pct"] < 0.5
    assert abs(v["fit"]["radius_mm"] - 7.7) < 0.02 and v["coverage_pct"] >= 90.0
    assert abs(v["mean_rel_error_pct"] - ref["mean_rel_error_pct"]) < 0.05
    m = manifest(result.run_dir)
    stage = m["devices"]["stage"]
    assert stage["backend"] == BACKEND[emulator] and stage["home"] == "on_connect"
    assert stage["identity"]["serial_number"] and stage["identity"]["firmware"]
    assert {"stop", "home", "angle_readback", "identity"} <= set(stage["capabilities"])
    assert [round(view["angle_read_deg"], 2) for view in m["views"]] == [0.0, 90.0, 180.0, 270.0]
    assert any("homed" in e.get("text", "") for e in events(result.run_dir))


def wait_for(predicate, timeout=20.0):
    t0 = time.monotonic()
    while not predicate():
        assert time.monotonic() - t0 < timeout, "timed out waiting"
        time.sleep(0.005)


def test_abort_during_a_move_stops_the_stage_within_half_a_second(tmp_path, dotshell_pm,
                                                                  serial_emulator):
    from dotshell.session.console import Session

    emu = serial_emulator("grbl", speed_deg_s=30.0)
    session = Session(emu_profile(tmp_path, "grbl", emu.port, views=4), pm=dotshell_pm,
                      out_dir=tmp_path / "runs")
    session.connect()
    job = session.scan(wait=False)
    wait_for(lambda: emu.state == "Run" and emu.angle > 5.0)
    t_abort = time.monotonic()
    session.abort()
    wait_for(lambda: emu.first_byte_time(b"!", t_abort) is not None, 2.0)
    latency = emu.first_byte_time(b"!", t_abort) - t_abort
    run = job.wait(30)
    assert latency < 0.5, latency
    assert run.status == "aborted" and emu.state == "Idle" and 5.0 < emu.angle < 85.0
    session.close()


def signal_during_a_move(tmp_path, emu, signum):
    """Run `dotshell scan` on the emulator, send ``signum`` mid-move; (latency until the
    emulator got the feed hold or None, exit code, stderr, the run's manifest)."""
    prof = emu_profile(tmp_path, "grbl", emu.port, views=4)
    proc = subprocess.Popen([sys.executable, "-m", "dotshell.cli.app", "scan", str(prof), "--out",
                             str(tmp_path / "runs")], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        wait_for(lambda: emu.state == "Run" and emu.angle > 5.0, 120.0)
        t_sig = time.monotonic()
        proc.send_signal(signum)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    hold = emu.first_byte_time(b"!", t_sig)
    [run] = list((tmp_path / "runs").iterdir())
    return None if hold is None else hold - t_sig, proc.returncode, err, manifest(run)


def test_ctrl_c_during_a_move_stops_the_stage_and_marks_the_run_aborted(tmp_path, serial_emulator):
    emu = serial_emulator("grbl", speed_deg_s=30.0)
    latency, code, err, m = signal_during_a_move(tmp_path, emu, signal.SIGINT)
    assert latency is not None and latency < 0.5, latency
    assert code == 130, err
    assert m["status"] == "aborted" and "Ctrl-C" in m["reason"]


def test_sigterm_during_a_move_stops_the_stage_and_marks_the_run_aborted(tmp_path,
                                                                        serial_emulator):
    emu = serial_emulator("grbl", speed_deg_s=30.0)
    latency, code, err, m = signal_during_a_move(tmp_path, emu, signal.SIGTERM)
    assert latency is not None and latency < 0.5, latency
    assert code == 130, err
    assert m["status"] == "aborted" and "SIGTERM" in m["reason"]


def test_unplugged_stage_is_reconnected_and_the_scan_goes_on(tmp_path, dotshell_pm,
                                                            serial_emulator):
    emu = serial_emulator("grbl", speed_deg_s=30.0)
    emu.faults.vanish_after_s, emu.faults.return_after_s = 0.1, 0.5
    # the port vanishes during the first move (for 0.5 s: several attempts to reopen it fail);
    # the second view's move (0.33 s) only shows the scan goes on
    profile = load_profile(emu_profile(tmp_path, "grbl", emu.port, views=2,
                                       angles_deg=[10.0, 20.0]), dotshell_pm)
    result = scan(profile, dotshell_pm, tmp_path / "runs")
    assert result.status == "completed" and emu.plugs == 2
    texts = [e.get("text", "") for e in events(result.run_dir)]
    assert any("lost during move_to()" in t and "reconnecting" in t for t in texts)
    assert any(t.endswith("reconnected") for t in texts)
    assert [v["complete"] for v in manifest(result.run_dir)["views"]] == [True, True]


def test_unplugged_stage_with_reconnect_off_fails_the_run_with_exit_2(tmp_path, capsys,
                                                                     serial_emulator):
    emu = serial_emulator("grbl", speed_deg_s=30.0)
    emu.faults.vanish_after_s, emu.faults.return_after_s = 0.1, 1.0
    prof = emu_profile(tmp_path, "grbl", emu.port, views=2, angles_deg=[10.0, 100.0])
    code = main(["scan", str(prof), "--out", str(tmp_path / "runs"),
                 "--set", "stage.reconnect=false"])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    flat = " ".join(err.split())
    assert f"grbl on {emu.port}" in flat and "reconnect = false" in flat
    [run] = list((tmp_path / "runs").iterdir())
    m = manifest(run)
    assert m["status"] == "failed" and "reconnect = false" in m["reason"]
    assert any(e["event"] == "ScanFinished" and "reconnect = false" in e["reason"]
               for e in events(run))


def test_failed_moves_are_retried_and_line_noise_is_logged(tmp_path, dotshell_pm,
                                                          serial_emulator):
    emu = serial_emulator("zaber", speed_deg_s=720.0)
    emu.faults.error = 1  # the first move is refused once
    emu.faults.garbage = True
    profile = load_profile(emu_profile(tmp_path, "zaber", emu.port, views=2), dotshell_pm,
                           ["stage.home=never"])
    result = scan(profile, dotshell_pm, tmp_path / "runs")
    assert result.status == "completed"
    texts = [(e.get("level"), e.get("text", "")) for e in events(result.run_dir)]
    retries = [t for level, t in texts if "retrying (1/2)" in t]
    assert len(retries) == 1 and "view 0: stage move to 0°" in retries[0]
    assert any(level == "warning" and "stage (zaber): noise on" in t for level, t in texts)


def test_home_before_scan_homes_the_stage_before_the_first_view(tmp_path, dotshell_pm,
                                                               serial_emulator):
    emu = serial_emulator("grbl", speed_deg_s=720.0)
    prof = emu_profile(tmp_path, "grbl", emu.port, views=2)
    profile = load_profile(prof, dotshell_pm, ["stage.home=before_scan"])
    scan(profile, dotshell_pm, tmp_path / "runs")
    commands = [c for _, c in emu.commands]
    assert commands.count("$H") == 1
    assert commands.index("$H") < next(i for i, c in enumerate(commands) if c.startswith("G90"))


class FaultyCameraPlugin:
    """The sim camera with frame metadata, or one whose capture breaks with a plain bug."""

    @hookimpl
    def dotshell_cameras(self):
        from dotshell_sim.devices import CAMERA_SCHEMA, SimCamera, make_camera

        class MetaCamera(SimCamera):
            def capture(self):
                frame = super().capture()
                self.info = FrameInfo(timestamp_s=time.time(), frame_id=self.frames,
                                      exposure_ms=self.exposure_ms, extra={"gain_db": 0.0})
                return frame

            def last_frame_info(self):
                return self.info

        class BuggyCamera(SimCamera):
            def capture(self):
                if self.frames == 40:
                    return np.zeros(3)[5]  # IndexError, a bug in the plugin
                return super().capture()

        def build(cls):
            def make(settings, context):
                cam = make_camera(settings, context)
                cam.__class__ = cls
                return cam
            return make

        return [Backend("meta-camera", build(MetaCamera), CAMERA_SCHEMA),
                Backend("buggy-camera", build(BuggyCamera), CAMERA_SCHEMA)]


def tiny(tmp_path, camera):
    raw = small_profile_dict(0.12, 2)
    raw["camera"]["backend"] = camera
    raw["camera"]["settings"]["supersample"] = 1
    raw["scan"]["acquisition"] = "show-capture"  # the wrapped cameras act in capture()
    raw["outputs"] = {"previews": False}
    return write_profile(tmp_path / "p.toml", raw)


def test_frame_metadata_is_written_next_to_the_frames(tmp_path):
    pm = PluginManager()
    pm.load_entry_points()
    pm.register(FaultyCameraPlugin(), name="faulty")
    result = scan(load_profile(tiny(tmp_path, "meta-camera"), pm), pm, tmp_path / "runs")
    m = manifest(result.run_dir)
    assert "frame_info" in m["devices"]["camera"]["capabilities"]
    info = json.loads((result.run_dir / m["views"][1]["frame_info"]).read_text())
    assert len(info) == m["views"][1]["frames"] == len(m["frame_names"])
    assert [i["name"] for i in info] == m["frame_names"]
    assert all(i["exposure_ms"] == 20.0 and i["gain_db"] == 0.0 for i in info)
    assert np.all(np.diff([i["timestamp_s"] for i in info]) >= 0)


def test_plugin_bug_is_a_named_fault_with_exit_2_and_the_run_kept(tmp_path, capsys, monkeypatch):
    import dotshell.plugins

    pm = PluginManager()
    pm.load_entry_points()
    pm.register(FaultyCameraPlugin(), name="faulty")
    monkeypatch.setattr(dotshell.plugins, "_default", pm)
    code = main(["scan", str(tiny(tmp_path, "buggy-camera")), "--out", str(tmp_path / "runs")])
    err = " ".join(capsys.readouterr().err.split())
    assert code == 2 and "Traceback" not in err
    assert "plugin 'faulty' (role camera, backend buggy-camera) raised IndexError" in err
    assert "in capture() (view 1, angle 180°, run" in err
    [run] = list((tmp_path / "runs").iterdir())
    m = manifest(run)
    assert m["status"] == "failed" and m["views"][0]["complete"]
    assert "plugin 'faulty' (role camera, backend buggy-camera) raised IndexError" in m["reason"]
    store = RunStore.open(run)
    assert sum(store.frames(v["index"]).count() for v in m["views"]) == 40


def test_session_connect_reopens_a_lost_stage_and_homes_on_request(tmp_path, dotshell_pm,
                                                                   serial_emulator):
    from dotshell.session.console import Session

    emu = serial_emulator("grbl", speed_deg_s=720.0)
    prof = emu_profile(tmp_path, "grbl", emu.port, views=2)
    session = Session(prof, pm=dotshell_pm, out_dir=tmp_path / "runs",
                      overrides=["stage.reconnect_wait_s=0.2"])
    session.connect()
    emu.unplug(back_after_s=1.0)
    with pytest.raises(DeviceLostError, match="did not come back within 0.2 s"):
        session.move_to(20)
    assert session.status()["stage"]["error"].startswith("lost")
    wait_for(lambda: emu.plugged, 5.0)
    session.connect()  # reopens the lost stage instead of skipping it
    assert session.move_to(20) == pytest.approx(20.0)
    assert session.home() == pytest.approx(0.0) and emu.angle == 0.0
    session.close()


def fault_profile(tmp_path, name, port):
    """A tiny scan in which the serial backend for ``name`` fills its role."""
    if name in BACKEND:
        raw = tomllib.loads(emu_profile(tmp_path, name, port, views=2).read_text())
        raw["stage"]["home"] = "never"
    else:
        raw = small_profile_dict(0.12, 2)
        raw["camera"]["settings"]["supersample"] = 1
        raw["outputs"] = {"previews": False}
        if name == "elliptec":
            raw["analyzer"] = {"backend": "elliptec", "settings": {"port": str(port)}}
            raw["scan"]["pdi"] = True
        else:
            raw["light_source"] = {"backend": "serial-switch", "settings": {"port": str(port)}}
            raw["transillumination"] = {"enabled": True, "flat_field": "none", "views": [0]}
    return write_profile(tmp_path / f"fault-{name}.toml", raw)


@pytest.mark.parametrize("name,device", [("grbl", "grbl"), ("zaber", "zaber"),
                                         ("apt", "thorlabs-apt"), ("elliptec", "elliptec"),
                                         ("switch", "serial-switch")])
def test_a_device_fault_mid_scan_fails_the_run_with_exit_2_and_the_reason_kept(
        tmp_path, capsys, serial_emulator, name, device):
    emu = serial_emulator(name, speed_deg_s=720.0)
    prof = fault_profile(tmp_path, name, emu.port)
    emu.faults.error = True  # every motion (or switching) command is refused
    code = main(["scan", str(prof), "--out", str(tmp_path / "runs")])
    err = " ".join(capsys.readouterr().err.split())
    assert code == 2 and "Traceback" not in err
    assert f"{device} on {emu.port}" in err
    [run] = list((tmp_path / "runs").iterdir())
    m = manifest(run)
    assert m["status"] == "failed" and f"{device} on {emu.port}" in m["reason"]
    assert any(e["event"] == "ScanFinished" and f"{device} on {emu.port}" in e["reason"]
               for e in events(run))
