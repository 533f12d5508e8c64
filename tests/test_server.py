"""The rig server on the simulated rig: the wire protocol, several clients with one in control,
the console served to front ends (input(), help(), completion, history), the logs, signals
and the command-line clients (serve, scan --detach, attach, status, stop) in real processes."""

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import write_test_profile
from dotshell.run.store import RunStore
from dotshell.session.console import PreviewSaved, Session
from dotshell.errors import DeviceError
from dotshell.events import FrameCaptured, ScanFinished, ScanStarted, ViewCaptured
from dotshell.server import protocol, server as server_module
from dotshell.server.client import RemoteSession
from dotshell.runtime.paths import server_log_dir, server_name, socket_path
from dotshell.server.protocol import ServerError, UnknownEvent, event_from_wire
from dotshell.server.repl import read_history
from rig_server import attach, served, user_dirs  # noqa: F401 (a fixture)


@pytest.fixture
def dirs(user_dirs):
    return user_dirs


@pytest.fixture
def session(tmp_path, pm, dirs):
    s = Session(write_test_profile(tmp_path, views=2), pm=pm, out_dir=tmp_path / "runs")
    yield s
    s.close()


class Inbox:
    """Every message a client receives; ``wait_for`` returns the latest that matches."""

    def __init__(self, client):
        self.messages, self.cond = [], threading.Condition()
        client.subscribe(self._put)

    def _put(self, m):
        with self.cond:
            self.messages.append(m)
            self.cond.notify_all()

    def wait_for(self, pred, timeout=60):
        with self.cond:
            assert self.cond.wait_for(lambda: any(pred(m) for m in self.messages), timeout), \
                f"never received it; got {[m.get('type') for m in self.messages][-20:]}"
            return [m for m in self.messages if pred(m)][-1]

    def of(self, kind):
        with self.cond:
            return [m for m in self.messages if m.get("type") == kind]


def events(inbox, name):
    return [m["event"] for m in inbox.of("event") if m["event"]["event"] == name]


# ---- the wire format ---------------------------------------------------------------------------

def test_events_cross_the_wire_as_themselves():
    ev = ScanFinished(status="completed", run_dir="r",
                      summary={"points": np.int64(7), "mean_rel_error_pct": np.float32(0.25)})
    back = event_from_wire(protocol.decode(protocol.encode({"e": ev.to_dict()}))["e"])
    assert back == ScanFinished(status="completed", run_dir="r", time=ev.time,
                                summary={"points": 7, "mean_rel_error_pct": 0.25})
    shot = PreviewSaved(kind="snap", path="p.png", stats={"histogram": np.arange(3)})
    assert event_from_wire(json.loads(json.dumps(shot.to_dict(), default=protocol._plain))) == \
        PreviewSaved(kind="snap", path="p.png", stats={"histogram": [0, 1, 2]}, time=shot.time)
    odd = event_from_wire({"event": "FromTheFuture", "time": 1.0, "x": 2})
    assert odd == UnknownEvent(name="FromTheFuture", fields={"x": 2}, time=1.0)
    with pytest.raises(DeviceError, match="not connected"):
        protocol.raise_remote({"ok": False, "kind": "DeviceError", "error": "not connected"})
    with pytest.raises(protocol.RemoteError) as info:
        protocol.raise_remote({"ok": False, "kind": "ZeroDivisionError", "error": "boom"})
    assert info.value.kind == "ZeroDivisionError"
    with pytest.raises(ServerError, match="not a protocol line"):
        protocol.decode(b"{nope")


def test_socket_is_private_and_named_after_the_profile(tmp_path, dirs):
    run_dir = socket_path("x").parent
    assert oct(run_dir.stat().st_mode & 0o777) == "0o700"
    a, b = tmp_path / "a" / "p.toml", tmp_path / "b" / "p.toml"
    assert server_name(a) != server_name(b) and server_name(a).startswith("p-")
    assert server_name(a) == server_name(str(a))
    with pytest.raises(ServerError, match="no rig server answers"):
        RemoteSession(socket_path("nobody"))


# ---- one session, several clients ----------------------------------------------------------------

def test_clients_watch_one_controls_and_everyone_sees_the_scan(session):
    with served(session) as server:
        assert oct(server.socket_path.stat().st_mode & 0o777) == "0o600"
        tui = attach(server, "tui")
        watcher = attach(server, "watcher", control=False)
        mine, theirs = Inbox(tui), Inbox(watcher)
        assert tui.in_control and not watcher.in_control
        tui.connect()
        assert tui.jog(12.5) == pytest.approx(12.5)
        with pytest.raises(ServerError, match=r"tui#1 \(pid \d+.*\) controls the rig"):
            watcher.jog(5)
        assert session.rig.stage.position == pytest.approx(12.5)  # the watcher moved nothing

        # a client that never reads must not hold the scan up
        stalled = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        stalled.connect(str(server.socket_path))
        stalled.sendall(protocol.encode({"id": 1, "cmd": "jog", "degrees": 1}))
        refused = protocol.decode(stalled.makefile("rb").readline())
        assert refused["ok"] is False and "first request must be hello" in refused["error"]
        stalled.sendall(protocol.encode({"id": 2, "cmd": "hello", "protocol": 99}))
        refused = protocol.decode(stalled.makefile("rb").readline())
        assert f"speaks protocol {protocol.PROTOCOL_VERSION}" in refused["error"]
        assert "99" in refused["error"]
        stalled.sendall(protocol.encode({"id": 3, "cmd": "hello",
                                         "protocol": protocol.PROTOCOL_VERSION,
                                         "client": "stalled"}))
        run_dir = tui.scan()["run_dir"]
        done = theirs.wait_for(lambda m: m.get("type") == "event"
                               and m["event"]["event"] == "ScanFinished")
        assert done["event"]["status"] == "completed" and done["event"]["run_dir"] == run_dir
        fpv = events(theirs, "ScanStarted")[0]["frames_per_view"]
        assert len(events(theirs, "FrameCaptured")) == len(events(mine, "FrameCaptured")) == 2 * fpv
        assert [e["view"] for e in events(theirs, "PreviewSaved") if e["kind"] == "frame"] == [0, 1]
        frame_stats = events(theirs, "PreviewSaved")[0]["stats"]
        assert frame_stats["width"] == session.rig.camera.resolution[0]
        assert sum(frame_stats["histogram"]) == frame_stats["width"] * frame_stats["height"]
        theirs.wait_for(lambda m: m.get("type") == "state" and m["state"]["session"] == "idle"
                        and m["state"]["run"] and m["state"]["run"]["dir"] == run_dir)
        assert json.loads((Path(run_dir) / "manifest.json").read_text())["status"] == "completed"
        # device status is pushed: the stage angle the scan left
        theirs.wait_for(lambda m: m.get("type") == "devices" and any(
            r["role"] == "stage" and r["status"].get("angle_deg") == pytest.approx(180.0)
            for r in m["rows"]))

        # control moves on request, and the one who lost it hears so
        watcher.take_control()
        mine.wait_for(lambda m: m.get("type") == "control")
        assert watcher.jog(-10) == pytest.approx(170.0)
        with pytest.raises(ServerError, match="watcher#2"):
            tui.jog(1)
        tui.close()
        watcher.close()
        stalled.close()

        log = server.log_path.read_text()
        assert "tui#1" in log and "attached in control" in log and "took control" in log
        assert "stage jogged +12.50° from 0.00° to 12.50°" in log
        run_log = (Path(run_dir) / "server.log").read_text()
        assert "scan started" in run_log and "scan completed" in run_log
        assert "stage jogged" not in run_log  # only what happened during the scan


def test_rows_and_state_pushed_while_a_client_is_greeted_reach_it_after_its_reply(session,
                                                                                monkeypatch):
    """The TUI's empty device table (seen once in a loaded test run): the server's poll pushed
    new device rows while a client's hello was being answered, and the client applied the
    reply's older rows after them; no later push came (the rows did not change again). Here
    the poll's pushes are made to happen in the middle of the hello, and the client's thread
    to be slow after it (a loaded machine)."""
    with served(session, poll_s=3600) as server:  # no poll but the ones forced here
        state, pushes, waited = server.state, [], []

        def state_during_hello():
            if threading.current_thread().name != "push" and not pushes:
                for push in (server._push_devices, server.push_state):
                    pushes.append(threading.Thread(target=push, name="push"))
                    pushes[-1].start()
                    pushes[-1].join(0.3)  # done at once, unless it waits for the hello's reply
                    waited.append(pushes[-1].is_alive())
            return state()

        call = RemoteSession.call

        def slow_after_hello(self, cmd, *args, **kwargs):
            result = call(self, cmd, *args, **kwargs)
            if cmd == "hello":
                time.sleep(0.3)  # the pushes after the reply arrive meanwhile
            return result

        monkeypatch.setattr(server, "state", state_during_hello)
        monkeypatch.setattr(RemoteSession, "call", slow_after_hello)
        client = attach(server, control=False)
        try:
            assert waited == [True, True]  # the server's pushes waited for the reply
            assert all(t.join(10) is None and not t.is_alive() for t in pushes)
            assert [r["role"] for r in client.rows] == ["camera", "projector", "stage"]
            assert client.rows == server._last_rows and client.state == server._last_state
        finally:
            client.close()


def test_a_watcher_may_halt_not_abort_and_the_server_exits_when_idle(session, monkeypatch):
    monkeypatch.setattr(server_module, "IDLE_GRACE_S", 0.5)
    gate = threading.Event()
    session.bus.subscribe(lambda ev: gate.wait(60) if isinstance(ev, FrameCaptured)
                          and (ev.view, ev.index) == (0, 1) else None)
    with served(session, exit_when_idle=True, poll_s=0.1) as server:
        tui, watcher = attach(server), attach(server, "watcher", control=False)
        run_dir = tui.scan()["run_dir"]
        with pytest.raises(ServerError, match="tui#1 .*controls the rig"):
            watcher.abort()  # aborting is the controller's
        assert watcher.halt() == "paused"  # the stop key is anyone's: it pauses, never aborts
        assert session.state == "paused"
        tui.abort()
        gate.set()
        tui.close()
        watcher.close()  # nobody attached: the server waits for the scan, then goes
        assert server.wait(60)
    assert json.loads((Path(run_dir) / "manifest.json").read_text())["status"] == "aborted"
    assert "exit_when_idle" in server.log_path.read_text()
    assert not server.socket_path.exists()


# ---- the console, served -------------------------------------------------------------------------

def test_console_input_help_completion_and_history(session, dirs):
    with served(session) as server:
        tui = attach(server)
        inbox = Inbox(tui)

        def run(source):
            n = len(inbox.of("console_done"))
            tui.console_run(source)
            return inbox.wait_for(lambda m: m.get("type") == "console_done"
                                  and len(inbox.of("console_done")) > n)

        tui.console_run("answer = input('angle? ')\nconnect(); move_to(float(answer))")
        asked = inbox.wait_for(lambda m: m.get("type") == "console_input")
        assert asked["prompt"] == "angle? "
        assert tui.console_reply("45")["delivered"]
        assert inbox.wait_for(lambda m: m.get("type") == "console_done")["ok"]
        assert session.rig.stage.position == pytest.approx(45.0)
        out = "".join(m["text"] for m in inbox.of("console") if m["kind"] == "out")
        assert "angle? 45\n" in out  # the prompt and the answer, as a terminal shows them

        tui.console_run("input('more? ')")  # ctrl+c while it waits: KeyboardInterrupt
        inbox.wait_for(lambda m: m.get("type") == "console_input" and m["prompt"] == "more? ")
        assert tui.console_interrupt()["interrupted"]
        done = inbox.wait_for(lambda m: m.get("type") == "console_done"
                              and len(inbox.of("console_done")) == 2)
        assert not done["ok"]
        assert "KeyboardInterrupt" in inbox.of("console")[-1]["text"]

        run("help(move_to)")
        text = "".join(m["text"] for m in inbox.of("console"))
        assert "Rotate the stage to an absolute angle" in text

        run("rig")
        assert inbox.of("console")[-1] == {"type": "console", "kind": "result", "text":
                                           "<Rig of sim-metal-cylinder: camera sim-camera, "
                                           "projector sim-projector, stage sim-turntable>"}
        assert tui.complete("rig.sta") == {"token": "rig.sta", "matches": ["rig.stage",
                                                                           "rig.status()"]}
        assert "move_to(" in tui.complete("x = mov")["matches"]
    # the history outlives the server
    history = read_history(dirs / "state" / "dotshell" / "console_history.jsonl")
    assert history[-2:] == ["help(move_to)", "rig"]
    assert history[0].startswith("answer = input(")
    with served(Session(pm=session.pm)) as server:
        assert attach(server).history[-2:] == ["help(move_to)", "rig"]


# ---- signals and the command-line clients, in real processes ---------------------------------------

def dotshell(*args, **kw):
    return subprocess.run([sys.executable, "-m", "dotshell.cli.app", *args], capture_output=True,
                          text=True, timeout=300, **kw)


def test_sigterm_aborts_the_scan_cleanly_and_sighup_can_be_kept(tmp_path, dirs):
    prof = write_test_profile(tmp_path, views=3)
    sock = socket_path("sig")
    proc = subprocess.Popen([sys.executable, "-m", "dotshell.cli.app", "serve", str(prof), "--out",
                             str(tmp_path / "runs"), "--socket", str(sock), "--on-hangup",
                             "keep"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        t0 = time.monotonic()
        while not sock.exists():
            assert proc.poll() is None and time.monotonic() - t0 < 120
            time.sleep(0.1)
        client = RemoteSession(sock, "test")
        inbox = Inbox(client)
        run_dir = Path(client.scan()["run_dir"])
        inbox.wait_for(lambda m: m.get("type") == "event" and m["event"]["event"] == "FrameCaptured")
        client.pause()
        inbox.wait_for(lambda m: m.get("type") == "event" and m["event"]["event"] == "ScanPaused")
        proc.send_signal(signal.SIGHUP)  # on_hangup = keep: nothing happens
        time.sleep(0.5)
        assert client.refresh()["state"]["session"] == "paused" and proc.poll() is None
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(120) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
    manifest = json.loads((run_dir / "manifest.json").read_text())
    assert manifest["status"] == "aborted"
    frames = sum(v["frames"] for v in manifest["views"])
    store = RunStore.open(run_dir)
    assert frames == sum(store.frames(v["index"]).count() for v in manifest["views"]) >= 1
    log = (server_log_dir("sig") / "server.log").read_text()
    assert "SIGHUP: kept running (on_hangup = keep)" in log
    assert "SIGTERM: aborting any scan cleanly" in log and "server stopped (SIGTERM)" in log
    assert inbox.wait_for(lambda m: m.get("type") == "bye")["reason"] == "SIGTERM"
    assert not sock.exists()


def test_scan_detach_attach_status_stop(tmp_path, dirs):
    prof = write_test_profile(tmp_path, views=2)
    out = tmp_path / "runs"
    started = dotshell("scan", str(prof), "--detach", "--out", str(out))
    assert started.returncode == 0, started.stderr
    assert "started the rig server" in started.stdout and "scan running:" in started.stdout
    run_dir = Path(started.stdout.split("scan running:")[1].split()[0])
    attached = dotshell("attach", str(prof))
    assert attached.returncode == 0, attached.stdout + attached.stderr
    assert "scan completed" in attached.stdout or "no scan is running; last run" in attached.stdout
    status = dotshell("status", "--json")
    info = json.loads(status.stdout)
    assert len(info) == 1 and info[0]["state"]["run"]["dir"] == str(run_dir)
    assert info[0]["state"]["run"]["status"] == "completed"
    assert dotshell("stop", str(prof)).returncode == 0
    assert "no rig server is running" in dotshell("status").stdout
    assert json.loads((run_dir / "manifest.json").read_text())["status"] == "completed"
