"""The scripting facade (Session), the console engine, `dotshell script`, the scan pause in the
acquisition runner and the progress tracker — headless, on the reduced simulated bench."""

import json
import shutil
import threading
import time

import numpy as np
import pytest

from conftest import write_test_profile
from dotshell.cli.app import main
from dotshell.session.console import PreviewSaved, Run, Session, SessionBusy, frame_stats, readable_repr
from dotshell.errors import DeviceError, ProfileError
from dotshell.events import (EventBus, FrameCaptured, ScanFinished, ScanPaused, ScanResumed,
                             ScanStarted, ViewCaptured, ViewReconstructed)
from dotshell.pipeline.scan import scan
from dotshell.profile.loader import load_profile
from dotshell.server.interpreter import Interpreter, wants_more
from dotshell.server.progress import ScanTracker, format_seconds
from dotshell.run.store import RunStore


@pytest.fixture
def session(tmp_path, pm):
    s = Session(write_test_profile(tmp_path), pm=pm, out_dir=tmp_path / "runs")
    yield s
    s.close()


# ---- pause and resume in the acquisition runner ---------------------------------------------

def test_scan_pauses_between_frames_and_resumes_to_completion(tmp_path, pm):
    profile = load_profile(write_test_profile(tmp_path), pm)
    running, bus, events = threading.Event(), EventBus(), []
    running.set()
    bus.subscribe(events.append)
    bus.subscribe(lambda ev: running.clear() if isinstance(ev, FrameCaptured)
                  and (ev.view, ev.index) == (1, 2) else None)
    result = {}
    worker = threading.Thread(target=lambda: result.update(
        r=scan(profile, pm, tmp_path / "runs", bus=bus, running=running)))
    worker.start()
    t0 = time.monotonic()
    while not any(isinstance(e, ScanPaused) for e in events):
        assert time.monotonic() - t0 < 60 and worker.is_alive()
        time.sleep(0.01)
    frames_at_pause = sum(isinstance(e, FrameCaptured) for e in events)
    time.sleep(0.5)
    assert sum(isinstance(e, FrameCaptured) for e in events) == frames_at_pause  # held
    assert worker.is_alive()
    fpv = next(e for e in events if isinstance(e, ScanStarted)).frames_per_view
    assert frames_at_pause == fpv + 3  # all of view 0, frames 0..2 of view 1
    paused = next(e for e in events if isinstance(e, ScanPaused))
    assert (paused.view, paused.index) == (1, 3)
    run_dir = next(e for e in events if isinstance(e, ScanStarted)).run_dir
    store = RunStore.open(run_dir)
    on_disk = sum(store.frames(v).count() for v in range(len(store.manifest["views"])))
    assert on_disk == frames_at_pause  # everything before the pause is written
    running.set()
    worker.join(60)
    r = result["r"]
    assert r.status == "completed"
    assert sum(isinstance(e, FrameCaptured) for e in events) == 2 * fpv
    assert [type(e).__name__ for e in events if isinstance(e, (ScanPaused, ScanResumed))] == [
        "ScanPaused", "ScanResumed"]
    assert all(v["complete"] for v in Run(r.run_dir).manifest["views"])
    wall_s = time.monotonic() - t0
    pause = [e for e in events if isinstance(e, (ScanPaused, ScanResumed))]
    paused_s = pause[1].time - pause[0].time
    assert paused_s >= 0.5
    assert r.report["timings_s"]["acquire"] <= wall_s - paused_s + 0.05  # pause not counted
    logged = [e["event"] for e in Run(r.run_dir).events()]
    assert "ScanPaused" in logged and "ScanResumed" in logged


def test_abort_while_paused_stops_cleanly(tmp_path, pm):
    profile = load_profile(write_test_profile(tmp_path), pm)
    running, stop, bus = threading.Event(), threading.Event(), EventBus()
    bus.subscribe(lambda ev: running.clear() if isinstance(ev, FrameCaptured)
                  and (ev.view, ev.index) == (0, 4) else None)
    bus.subscribe(lambda ev: stop.set() if isinstance(ev, ScanPaused) else None)
    running.set()
    r = scan(profile, pm, tmp_path / "runs", bus=bus, stop=stop, running=running)
    assert r.status == "aborted"
    assert Run(r.run_dir).frame_count() == 5


# ---- the Session facade ----------------------------------------------------------------------

def test_session_drives_the_rig(session):
    with pytest.raises(DeviceError, match="connect the rig first"):
        session.jog(5)
    status = session.connect()
    assert set(status) == {"camera", "projector", "stage"} and session.connected
    assert session.jog(10) == pytest.approx(10.0)
    assert session.jog(-25) == pytest.approx(-15.0)
    assert session.move_to(90) == pytest.approx(90.0)
    assert session.status()["stage"]["angle_deg"] == pytest.approx(90.0)
    with pytest.raises(DeviceError, match="no \\[analyzer\\] device"):
        session.set_analyzer(45)
    assert session.set_exposure(10) == 10.0
    assert session.status()["camera"]["exposure_ms"] == 10.0

    names = session.patterns()
    assert names[:2] == ["white", "black"] and len(names) > 10
    previews = []
    session.bus.subscribe(lambda ev: previews.append(ev) if isinstance(ev, PreviewSaved) else None)
    session.project("white")
    white = session.snap()
    session.project("black")
    black = session.snap()
    w, h = session.rig.camera.resolution
    assert white.frame.shape == (h, w) and white.path.name == "snap_0001.png"
    assert black.path.name == "snap_0002.png" and black.preview.is_file()
    assert white.frame.mean() > 5 * black.frame.mean()
    assert [p.kind for p in previews] == ["snap", "snap"]
    with pytest.raises(DeviceError, match="no pattern 'nope'"):
        session.project("nope")

    decoded = session.decode()
    assert decoded.preview.is_file()
    assert 0.05 < decoded.decoded_pixels / decoded.total_pixels < 1.0
    session.disconnect()
    assert not session.connected


def test_session_background_scan_pause_resume_and_busy_guard(session):
    session.connect()
    gate = threading.Event()
    session.bus.subscribe(lambda ev: gate.wait(30) if isinstance(ev, FrameCaptured)
                          and (ev.view, ev.index) == (0, 1) else None)
    job = session.scan(wait=False)
    assert repr(job).startswith("ScanJob(running for ")
    with pytest.raises(SessionBusy, match="while a scan is running"):
        session.jog(5)
    with pytest.raises(SessionBusy):
        session.scan()
    session.pause()
    assert session.state == "paused"
    gate.set()
    time.sleep(0.3)
    assert session.state == "paused" and not job.done
    session.resume()
    run = session.wait(60)
    assert run.status == "completed" and session.state == "idle"
    assert repr(job) == f"ScanJob(done: {run!r})"
    assert run is session.run and len(run.cloud()) > 1000
    assert session.jog(5) == pytest.approx(185.0)  # free again, still at the last view


def test_session_abort_keeps_frames_and_marks_the_run_aborted(session):
    session.bus.subscribe(lambda ev: session.abort() if isinstance(ev, ViewCaptured) else None)
    run = session.scan()
    assert run.status == "aborted"
    fpv = len(run.manifest["frame_names"])
    assert run.frame_count() == fpv  # view 0 complete, stopped before view 1
    assert [v["view"] for v in run.report["views"]] == [0]  # the complete view is processed
    assert len(run.cloud()) == run.report["cloud"]["points"] > 0


def test_session_set_changes_the_profile(session):
    session.connect()
    session.set("scan.views=3")
    assert len(session.profile.angles_deg()) == 3 and session.connected
    with pytest.raises(ProfileError):
        Session(pm=session.pm).connect()


def test_namespace_follows_the_session(session):
    ns = session.namespace()
    assert ns["profile"] is session.profile and ns["run"] is None
    ns["connect"]()
    run = ns["scan"]()
    assert ns["run"] is run and ns["rig"] is session.rig
    assert isinstance(ns["np"].zeros(1), np.ndarray)


# ---- the console engine ----------------------------------------------------------------------

def test_interpreter_results_output_and_errors():
    out = []
    interp = Interpreter({}, lambda kind, text: out.append((kind, text)))
    assert interp.run("x = 6\nprint('x is', x)\nx * 7")
    assert "".join(t for k, t in out if k == "out") == "x is 6\n"
    assert out[-1] == ("result", "42")
    assert not interp.run("undefined_name + 1")
    assert out[-1][0] == "error" and "NameError" in out[-1][1] and "<console#2>" in out[-1][1]
    assert not interp.run("if True print(1)")
    assert out[-1][0] == "error" and out[-1][1].startswith('  File "<console#3>"')
    assert "SyntaxError" in out[-1][1]
    assert interp.run("x")  # the namespace survived the errors
    assert out[-1] == ("result", "6")


def test_interpreter_interrupts_a_running_loop():
    out = []
    interp = Interpreter({}, lambda kind, text: out.append((kind, text)))
    done = []
    worker = threading.Thread(target=lambda: done.append(interp.run("n = 0\nwhile True:\n n += 1")))
    worker.start()
    while interp.namespace.get("n", 0) < 1000:
        time.sleep(0.01)
    assert interp.busy and interp.interrupt()
    worker.join(10)
    assert done == [False] and "KeyboardInterrupt" in out[-1][1]
    assert not interp.busy and not interp.interrupt()


def test_wants_more_follows_the_repl_rules():
    assert not wants_more("1 + 1")
    assert wants_more("for i in range(3):")
    assert wants_more("for i in range(3):\n    print(i)")  # still in the block
    assert not wants_more("for i in range(3):\n    print(i)\n")  # blank line ends it
    assert wants_more("x = (1,")
    assert not wants_more("x = 1\ny = 2")
    assert not wants_more("def f(:")  # run it, to show the error


# ---- dotshell script ----------------------------------------------------------------------------

def test_script_command_runs_against_the_facade(tmp_path, capsys):
    prof = write_test_profile(tmp_path)
    script = tmp_path / "measure.py"
    script.write_text(
        "import json, sys\n"
        "connect()\n"
        "angles = [jog(float(sys.argv[1])) for _ in range(3)]\n"
        "frame = snap().frame\n"
        "run = scan()\n"
        "json.dump({'angles': angles, 'shape': list(frame.shape), 'status': run.status,\n"
        "           'points': len(run.cloud()), 'profile': profile.name},\n"
        "          open(sys.argv[2], 'w'))\n")
    out = tmp_path / "result.json"
    code = main(["script", str(script), "--profile", str(prof), "--out", str(tmp_path / "runs"),
                 "--set", "scan.views=2", "--", "12.5", str(out)])
    assert code == 0
    res = json.loads(out.read_text())
    assert res["angles"] == [12.5, 25.0, 37.5]
    assert res["status"] == "completed" and res["points"] > 1000
    assert res["profile"] == "sim-metal-cylinder"
    runs = [p for p in (tmp_path / "runs").iterdir() if p.name != "snapshots"]
    assert len(runs) == 1 and (runs[0] / "cloud.ply").is_file()


def test_script_errors_are_user_errors(tmp_path, capsys):
    script = tmp_path / "bad.py"
    script.write_text("connect()\n")
    assert main(["script", str(script)]) == 2  # no profile loaded
    assert "no profile is loaded" in capsys.readouterr().err
    assert main(["script", str(tmp_path / "missing.py")]) == 2
    assert "cannot read script" in capsys.readouterr().err


# ---- progress tracking ------------------------------------------------------------------------

def test_tracker_counts_and_eta_exclude_pauses():
    t = ScanTracker()
    t.update(ScanStarted(run_dir="r", profile="p", n_views=2, frames_per_view=5), 100.0)
    for i in range(5):
        t.update(FrameCaptured(view=0, index=i, name=f"f{i}"), 100.0 + i + 1)
    t.update(ViewCaptured(view=0, angle_deg=0.0, n_frames=5), 105.0)
    t.update(ViewReconstructed(view=0, n_points=1000, decoded_pixels=2000), 105.0)
    assert t.eta_s(105.0) == pytest.approx(5.0)  # 1 s a frame, 5 frames left
    t.update(ScanPaused(view=1, index=0), 105.0)
    assert t.eta_s(125.0) == pytest.approx(5.0)  # the pause does not count
    t.update(ScanResumed(view=1, index=0), 125.0)
    assert t.active_seconds(126.0) == pytest.approx(6.0)
    t.update(ScanFinished(status="aborted", run_dir="r", summary={"points": 1000}), 126.0)
    assert (t.status, t.frames_done, t.views_done, t.points) == ("aborted", 5, 1, 1000)
    assert t.eta_s(130.0) is None
    assert format_seconds(3725) == "1:02:05" and format_seconds(None) == "--:--"


def test_eta_ignores_the_warm_up():
    """Ten minutes of connecting, calibration and flat field before the first frame, then a
    frame a second: the ETA is a second a frame, not the warm-up spread over the frames."""
    t = ScanTracker()
    t.update(ScanStarted(run_dir="r", profile="p", n_views=4, frames_per_view=5), 0.0)
    t.update(FrameCaptured(view=0, index=0, name="f0"), 600.0)
    assert t.eta_s(600.5) is None  # one frame says nothing about the rate yet
    for i in range(1, 5):
        t.update(FrameCaptured(view=0, index=i, name=f"f{i}"), 600.0 + i)
    t.update(ViewCaptured(view=0, angle_deg=0.0, n_frames=5), 604.0)
    assert t.eta_s(604.0) == pytest.approx(15.0)  # 15 frames left at 1 s
    t.update(ScanPaused(view=0, index=5), 604.0)
    t.update(ScanResumed(view=0, index=5), 700.0)
    assert t.eta_s(700.0) == pytest.approx(15.0)  # the pause does not count either
    assert t.active_seconds(700.0) == pytest.approx(604.0)
    again = ScanTracker.from_dict(json.loads(json.dumps(t.to_dict())))
    assert again == t  # what the server sends a front end that attaches now


def test_tracker_uses_the_events_own_times():
    t = ScanTracker()
    t.update(ScanStarted(run_dir="r", profile="p", n_views=1, frames_per_view=3, time=50.0))
    for i in range(3):
        t.update(FrameCaptured(view=0, index=i, name="f", time=51.0 + i))
    t.update(ScanFinished(status="completed", run_dir="r", summary={"points": 0}, time=60.0))
    assert t.active_seconds(1e9) == pytest.approx(10.0)
    assert t.status == "completed" and t.shown_status == "failed"  # no points: not a success


def test_frame_stats_describe_the_raw_frame():
    frame = np.zeros((10, 20), np.uint16)
    frame[0, :5] = 4095  # 5 saturated pixels of a 12-bit camera
    frame[1, :] = 2000
    stats = frame_stats(frame, bit_depth=12)
    assert (stats["width"], stats["height"]) == (20, 10)
    assert (stats["min"], stats["max"], stats["full_scale"]) == (0.0, 4095.0, 4095.0)
    assert stats["saturated_pct"] == pytest.approx(2.5)
    assert stats["mean"] == pytest.approx(frame.mean())
    assert sum(stats["histogram"]) == 200 and stats["histogram"][0] == 175
    assert stats["histogram"][-1] == 5 and stats["histogram"][15] == 20  # 2000 of 0..4095
    assert frame_stats(np.full((2, 2), 255, np.uint8))["saturated_pct"] == 100.0


def test_stop_stops_the_devices_without_waiting_for_a_move(session, monkeypatch):
    session.connect()
    stops, moving, released = [], threading.Event(), threading.Event()
    monkeypatch.setattr(session.rig, "stop", lambda: stops.append(time.monotonic()))
    move = session.rig.stage.move_to

    def slow_move(deg):
        moving.set()
        released.wait(30)
        move(deg)

    monkeypatch.setattr(session.rig.stage, "move_to", slow_move)
    mover = threading.Thread(target=session.jog, args=(10,))
    mover.start()
    assert moving.wait(30)
    session.stop()  # the jog holds the session: stop must not wait for it
    assert len(stops) == 1 and mover.is_alive()
    released.set()
    mover.join(30)


def test_readable_reprs(session):
    assert readable_repr(session.rig) == ("<Rig of sim-metal-cylinder: camera sim-camera "
                                          "(closed), projector sim-projector (closed), stage "
                                          "sim-turntable (closed)>")
    assert readable_repr(session.profile).startswith("<Profile sim-metal-cylinder from ")
    assert "2 views, exposure 20 ms, coding graycode>" in readable_repr(session.profile)
    assert readable_repr([1, 2]) == "[1, 2]"


def test_a_run_nobody_writes_any_more_reads_interrupted(small_scan, tmp_path):
    """The manifest says ``running`` but no process holds the run: the session says
    ``interrupted`` (the engine's view), not ``running`` for good."""
    result, _ = small_scan
    copy = tmp_path / "run"
    shutil.copytree(result.run_dir, copy, symlinks=True)
    manifest = json.loads((copy / "manifest.json").read_text())
    manifest["status"] = "running"
    (copy / "manifest.json").write_text(json.dumps(manifest))
    status, reason = Run(copy).status_and_reason()
    assert status == "interrupted" and "ended without finishing" in reason
    (copy / "manifest.json").write_text("{}")
    assert Run(copy).status_and_reason()[0] == "unknown"  # damaged: said, not raised


# ---- one namespace for the console and scripts (issue 29) ----------------------------------

SCRIPT_WITH_MAIN = (
    "import argparse, sys\n"
    "def main():\n"
    "    p = argparse.ArgumentParser()\n"
    "    p.add_argument('step', type=float)\n"
    "    p.add_argument('--times', type=int, default=1)\n"
    "    a = p.parse_args()\n"
    "    global angles, argv\n"
    "    argv = list(sys.argv)\n"
    "    connect()\n"
    "    angles = [jog(a.step) for _ in range(a.times)]\n"
    "if __name__ == '__main__':\n"
    "    main()\n")


def console_of(session):
    from dotshell.server.repl import ServerConsole

    messages = []
    console = ServerConsole(session, messages.append)

    def run(source):
        n = sum(m["type"] == "console_done" for m in messages)
        console.run(source)
        t0 = time.monotonic()
        while sum(m["type"] == "console_done" for m in messages) == n:
            assert time.monotonic() - t0 < 120
            time.sleep(0.02)

    return console, messages, run


def test_run_script_in_the_console_is_main_with_its_own_argv(session, tmp_path):
    """The bug: in the console __name__ was 'builtins' and sys.argv the server's, so a script's
    `if __name__ == "__main__": main()` silently did nothing and argument parsing failed."""
    import sys

    script = tmp_path / "sweep.py"
    script.write_text(SCRIPT_WITH_MAIN)
    console, messages, run = console_of(session)
    argv_before = list(sys.argv)
    run(f"r = run_script({str(script)!r}, 2.5, '--times', 3)\nprint(r.angles, r.argv)\nr")
    out = "".join(m.get("text", "") for m in messages if m.get("kind") == "out")
    assert out == f"[2.5, 5.0, 7.5] [{str(script)!r}, '2.5', '--times', '3']\n"
    result = [m["text"] for m in messages if m.get("kind") == "result"][-1]
    assert result == f"<script {script} ran: defined main, argv, angles>"  # not its imports
    assert sys.argv == argv_before  # restored
    assert session.rig.stage.position == pytest.approx(7.5)
    # the console itself is __main__ too: the same code pasted runs its main()
    run("import sys; sys.argv[1:] = ['1', '--times', '2']\n" + SCRIPT_WITH_MAIN
        + "sys.argv[1:] = []\nangles")
    assert [m["text"] for m in messages if m.get("kind") == "result"][-1] == "[8.5, 9.5]"
    # argparse's exit status 2 is an error; a clean sys.exit() ends a script quietly
    run(f"run_script({str(script)!r})")
    assert "SystemExit: 2" in [m["text"] for m in messages if m.get("kind") == "error"][-1]
    script.write_text("import sys\nsys.exit()\n")
    run(f"run_script({str(script)!r}) is not None")
    assert [m["text"] for m in messages if m.get("kind") == "result"][-1] == "True"


def test_console_scan_prints_progress_not_per_frame_lines(session):
    """scan() in the console shows the session's progress from the info level on: a line per
    view captured and reconstructed, the steps and the end — not one per frame."""
    console, messages, run = console_of(session)
    run("connect(); r = scan()")
    lines = "".join(m["text"] for m in messages if m.get("kind") == "log").splitlines()
    frames = session.run.frame_count()
    assert frames == 2 * len(session.run.manifest["frame_names"]) > 20
    assert not any("frame" in line and "captured" in line and "view" in line
                   and "frames)" not in line for line in lines)
    assert sum(line.startswith("view ") and "captured at" in line for line in lines) == 2
    assert sum("reconstructed" in line for line in lines) == 2
    assert sum(line.startswith("scan started") for line in lines) == 1
    assert lines[-1].startswith("scan completed")
    assert len(lines) < 30  # was ≈ 190 lines for 4 views
    run("log_level('debug'); r = scan()")
    debug = "".join(m["text"] for m in messages if m.get("kind") == "log").splitlines()
    assert sum("debug: view" in line and ") captured" in line for line in debug) == frames
    run("log_level('loud')")
    assert "choose one of debug, info, warning, error or off" in [
        m["text"] for m in messages if m.get("kind") == "error"][-1]


def test_the_eta_says_estimating_until_a_view_is_captured():
    """The bug: the first frames of a view come in a burst, so at 0:03 of a 25 s scan the ETA
    said 0:00:02 (the rate without the moves and the reconstruction between views). Now it
    says estimating until a whole view has been captured, and finishing after the last frame."""
    t = ScanTracker()
    t.update(ScanStarted(run_dir="r", profile="p", n_views=4, frames_per_view=10), 0.0)
    assert t.eta_text(0.5) == "estimating"
    for i in range(10):  # a burst: 0.1 s a frame
        t.update(FrameCaptured(view=0, index=i, name=f"f{i}"), 2.0 + 0.1 * i)
        assert t.eta_text(2.0 + 0.1 * i) == "estimating"
    t.update(ViewCaptured(view=0, angle_deg=0.0, n_frames=10), 3.0)
    # 5 s of move and reconstruction, then the next view's burst: the rate includes them
    for i in range(10):
        t.update(FrameCaptured(view=1, index=i, name=f"f{i}"), 8.0 + 0.1 * i)
    t.update(ViewCaptured(view=1, angle_deg=90.0, n_frames=10), 9.0)
    eta = t.eta_s(9.0)
    assert eta == pytest.approx((9.0 - 2.0) / 19 * 20)  # 7.4 s for the last 2 views, not 2 s
    for v in (2, 3):
        for i in range(10):
            t.update(FrameCaptured(view=v, index=i, name=f"f{i}"), 9.0 + v + 0.1 * i)
    assert t.eta_text(14.0) == "finishing"  # merge, validate, previews: not timed
    t.update(ScanFinished(status="completed", run_dir="r", summary={"points": 9}), 20.0)
    assert t.eta_text(20.0) == "--:--"


def test_exposure_is_the_scans_and_a_refused_one_never_reaches_the_camera(session):
    """set_exposure sets the camera and scan.exposure_ms (the scan used the profile's value);
    configure changes the next scan's keys without reconnecting the rig."""
    session.connect()
    rig = session.rig
    assert session.set_exposure(7.5) == 7.5
    assert session.profile.data["scan"]["exposure_ms"] == 7.5
    assert rig.camera.status()["exposure_ms"] == 7.5
    with pytest.raises(ProfileError, match="exposure_ms"):
        session.set_exposure(0.0)  # below the profile's minimum
    assert rig.camera.status()["exposure_ms"] == 7.5 and session.rig is rig
    session.configure(views=3, pdi_angles_deg=[5, 95], out_dir=session.out_dir / "next")
    assert session.rig is rig and session.connected  # kept, not rebuilt
    run = session.scan()
    assert len(run.manifest["views"]) == 3 and run.root.parent.name == "next"
    assert run.manifest["camera"] and "exposure_ms = 7.5" in (run.root / "profile.toml").read_text()


def test_a_script_has_the_consoles_names_and_log_level(tmp_path, capsys):
    """dotshell script and the console share one namespace: __main__, run_script, log_level;
    the script's log lines follow log_level() as the console's do."""
    script = tmp_path / "levels.py"
    script.write_text(
        "from dotshell.events import Message\n"
        "print(__name__, log_level(), callable(run_script))\n"
        "session.bus.emit(Message('debug', 'a debug line'))\n"
        "session.bus.emit(Message('info', 'an info line'))\n"
        "log_level('warning')\n"
        "session.bus.emit(Message('info', 'a hidden info line'))\n"
        "session.bus.emit(Message('warning', 'a warning line'))\n")
    assert main(["script", str(script)]) == 0
    out, err = capsys.readouterr()
    assert out == "__main__ info True\n"
    assert "an info line" in err and "a warning line" in err
    assert "a debug line" not in err and "a hidden info line" not in err
