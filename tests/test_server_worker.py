"""The session in a worker process: a camera driver that hangs in C holding the GIL stops only
the worker. The server keeps answering its clients, names the hung call, ends the worker when
a scan is aborted (run ``aborted``, every written frame kept) and restarts it on request."""

import ctypes
import json
import os
import re
import subprocess
import sys
import threading
import time
import tomllib
from contextlib import contextmanager
from pathlib import Path

import pytest
import tomli_w

from conftest import make_dist, write_test_profile
from dotshell.server.client import RemoteSession
from dotshell.runtime.paths import server_name, socket_path
from dotshell.server.protocol import ServerError
from dotshell.server.supervisor import WorkerSession
from dotshell.run.store import RunStore
from rig_server import attach, served, user_dirs  # noqa: F401 (a fixture)
from test_server import Inbox

#: A camera backend: the simulated camera, whose capture() calls libc's sleep through
#: ctypes.PyDLL (which, unlike CDLL, keeps the GIL during the call) once a flag file exists:
#: a driver stuck in C that no Python thread of its process can get past.
HUNG_CAMERA = '''
import ctypes, os
from dotshell import hookimpl
from dotshell.backends import Backend
from dotshell_sim.devices import CAMERA_SCHEMA, make_camera

_libc = ctypes.PyDLL("libc.so.6")


def make_hung_camera(settings=None, context=None):
    camera = make_camera(settings, context)
    capture = camera.capture

    def hanging_capture():
        if os.path.exists(os.environ["DOTSHELL_TEST_HANG_FLAG"]):
            _libc.sleep(3600)
        return capture()

    camera.capture = hanging_capture
    return camera


@hookimpl
def dotshell_cameras():
    return [Backend("hung-camera", make_hung_camera, CAMERA_SCHEMA,
                    "the sim camera, hanging in C with the GIL held once a flag file exists")]
'''


@pytest.fixture
def hung_rig(tmp_path, user_dirs, monkeypatch):
    """(profile, flag): a 3-view sim profile whose camera hangs once ``flag`` exists; the
    plugin is installed for the worker processes (PYTHONPATH)."""
    site = make_dist(tmp_path / "site", "dotshell-hung", "dotshell_hung_camera", HUNG_CAMERA,
                     "hung")
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(site),
                                                       os.environ.get("PYTHONPATH", "")]))
    flag = tmp_path / "hang"
    monkeypatch.setenv("DOTSHELL_TEST_HANG_FLAG", str(flag))
    prof = write_test_profile(tmp_path, views=3)
    raw = tomllib.loads(prof.read_text())
    raw["camera"]["backend"] = "hung-camera"
    prof.write_text(tomli_w.dumps(raw))
    return prof, flag


def _ticks_during(lib, seconds: float) -> int:
    """How often another thread counted while ``lib.usleep`` ran in this one."""
    count, stop = [0], threading.Event()

    def tick():
        while not stop.is_set():
            count[0] += 1

    t = threading.Thread(target=tick)
    t.start()
    while count[0] < 1000:  # the counter runs
        pass
    before = count[0]
    lib.usleep(int(seconds * 1e6))
    after = count[0]
    stop.set()
    t.join()
    return after - before


def test_pydll_holds_the_gil_where_cdll_releases_it():
    """The fake driver's premise: through PyDLL no other thread runs during the C call (at most
    the switch interval before it); through CDLL it runs the whole time."""
    held = _ticks_during(ctypes.PyDLL("libc.so.6"), 0.5)
    released = _ticks_during(ctypes.CDLL("libc.so.6"), 0.5)
    assert held * 4 < released, (held, released)


def test_the_call_board_names_the_call_that_holds_up_the_others():
    """Two calls in progress: one thread blocked on a lock (as a call waiting for the GIL is),
    one running (this thread); the board, read through its own mapping, names the running one
    and lists the other as waiting behind it."""
    from dotshell.server.callboard import CallBoard, _on_futex

    board, reader = CallBoard(), None
    lock, tids = threading.Lock(), {}
    lock.acquire()

    def blocked():
        tids["blocked"] = threading.get_native_id()
        lock.acquire()

    threading.Thread(target=blocked, daemon=True).start()
    try:
        _wait_until(lambda: "blocked" in tids and _on_futex(os.getpid(), tids["blocked"]))
        board.enter("stage (sim-turntable)", "status", tids["blocked"])
        reader = CallBoard(os.dup(board.fd))  # the server's side: its own mapping of the page
        assert reader.describe(os.getpid()).startswith("stage (sim-turntable) status() for ")
        # a lone call on a lock is named (nothing tells it apart from a culprit)
        board.enter("camera (hung-camera)", "capture", threading.get_native_id())
        text = reader.describe(os.getpid())  # this thread reads: not on a futex
        assert text.startswith("camera (hung-camera) capture() for ")
        assert "(waiting behind it: stage (sim-turntable) status() for " in text
        board.leave("camera (hung-camera)")
        board.leave("stage (sim-turntable)")
        assert reader.read() == {} and reader.describe(os.getpid()) == ""
    finally:
        lock.release()
        board.close()
        if reader is not None:
            reader.close()


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def _frames_on_disk(run_dir: Path) -> int:
    try:
        return RunStore.open(run_dir).frames(0).count()
    except Exception:  # the stack is not there yet
        return 0


def _wait_until(condition, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "the condition never came true"
        time.sleep(0.05)


def _worker(m):
    return (m.get("state") or {}).get("worker") or {}


@contextmanager
def _hung_scan(hung_rig, tmp_path, name):
    """A server on the hung camera (hang_s 2 s, abort_bound_s 3 s), a controller that starts
    a scan and a watcher; yields once a frame is on disk and the camera then hung the worker:
    (session, server, watcher, its inbox, run_dir, the first state message saying hung)."""
    prof, flag = hung_rig
    session = WorkerSession(prof, out_dir=tmp_path / "runs", hang_s=2.0, abort_bound_s=3.0)
    with served(session, name=name, poll_s=0.1) as server:
        controller = attach(server)
        watcher = attach(server, "watcher", control=False)
        inbox = Inbox(watcher)
        run_dir = Path(controller.scan()["run_dir"])
        _wait_until(lambda: _frames_on_disk(run_dir) >= 1)  # (frames are written behind)
        flag.touch()  # the next capture() hangs in C with the GIL held
        hung = inbox.wait_for(lambda m: m.get("type") == "state"
                              and _worker(m).get("state") == "hung", timeout=120)
        yield session, server, watcher, inbox, run_dir, hung


def test_a_driver_hung_in_c_leaves_the_server_answering_and_stop_abort_ends_the_scan(hung_rig,
                                                                                      tmp_path):
    with _hung_scan(hung_rig, tmp_path, "hung") as (session, server, watcher, inbox, run_dir,
                                                    hung):
        first_pid = session.pid
        assert "camera (hung-camera) capture() for" in _worker(hung)["hung"]
        assert _pid_alive(first_pid)
        # the server answers every client while the worker is stuck: replies and pushes
        for _ in range(5):
            state = watcher.refresh()["state"]
            assert state["worker"]["state"] == "hung" and state["session"] == "running"
        assert [r["role"] for r in watcher.call("devices")] == ["camera", "projector", "stage"]
        silent = _worker(hung)["silent_s"]  # pushed as it grows, every second while hung
        inbox.wait_for(lambda m: m.get("type") == "state" and _worker(m).get("silent_s", 0)
                       >= silent + 2)
        assert session.pid == first_pid and _pid_alive(first_pid)
        log = inbox.wait_for(lambda m: m.get("type") == "event"
                             and "has not answered" in m["event"].get("text", ""))
        assert "camera (hung-camera) capture()" in log["event"]["text"]

        status = subprocess.run([sys.executable, "-m", "dotshell.cli.app", "status", "--server",
                                 "hung"], capture_output=True, text=True, timeout=300)
        assert re.search(rf"worker +pid {first_pid}, hung in camera \(hung-camera\) capture\(\) "
                         r"for [\d.]+ s.*\(silent \d+ s\)", " ".join(status.stdout.split())), \
            status.stdout
        stopped = subprocess.run([sys.executable, "-m", "dotshell.cli.app", "stop", "--server",
                                  "hung", "--abort"], capture_output=True, text=True,
                                 timeout=300)
        assert stopped.returncode == 0, stopped.stdout + stopped.stderr
        assert "stopped" in stopped.stdout
        assert server.wait(120)
    assert not _pid_alive(first_pid)
    finished = [m["event"] for m in inbox.of("event") if m["event"]["event"] == "ScanFinished"]
    assert [f["status"] for f in finished] == ["aborted"]
    assert "camera (hung-camera) capture()" in finished[0]["reason"]
    manifest = json.loads((run_dir / "manifest.json").read_text())
    assert manifest["status"] == "aborted"
    assert "within 3 s of the stop; it was inside camera (hung-camera) capture() for" \
        in manifest["reason"]  # first: a poll's status() call waits behind it, for the GIL
    store = RunStore.open(run_dir)
    on_disk = sum(store.frames(v["index"]).count() for v in manifest["views"])
    captured = [m for m in inbox.of("event") if m["event"]["event"] == "FrameCaptured"]
    assert sum(v["frames"] for v in manifest["views"]) == on_disk >= 1
    assert on_disk <= len(captured)  # a frame captured but still queued for writing is not
    assert store.events()[-1]["event"] == "ScanFinished"
    assert RunStore.open(run_dir).status()[0] == "aborted"


def test_a_hung_worker_is_restarted_and_the_new_one_works(hung_rig, tmp_path):
    prof, flag = hung_rig
    session = WorkerSession(prof, out_dir=tmp_path / "runs", hang_s=2.0)
    first_pid = session.pid
    with served(session, name="hung2", poll_s=0.1) as server:
        controller = attach(server)
        inbox = Inbox(controller)
        loaded = tmp_path / "q.toml"  # a profile loaded later is what the new worker loads
        loaded.write_text(prof.read_text().replace("views = 3", "views = 2"))
        assert controller.load(loaded)["views"] == 2
        controller.connect()
        flag.touch()
        failed: list[BaseException] = []
        snapping = threading.Thread(target=lambda: _catch(controller.snap, failed))
        snapping.start()
        inbox.wait_for(lambda m: m.get("type") == "state" and _worker(m).get("state") == "hung",
                       timeout=120)
        flag.unlink()
        restarted = subprocess.run([sys.executable, "-m", "dotshell.cli.app", "stop", "--server",
                                    "hung2", "--restart-worker"], capture_output=True, text=True,
                                   timeout=300)
        assert restarted.returncode == 0, restarted.stdout + restarted.stderr
        assert "session worker restarted" in restarted.stdout
        snapping.join(60)
        assert not snapping.is_alive() and failed
        assert "was ended: restart requested" in str(failed[0])
        assert not _pid_alive(first_pid) and session.pid != first_pid
        state = controller.refresh()["state"]
        assert state["worker"]["restarts"] == 1 and state["worker"]["state"] == "running"
        assert state["connected"] is False and state["profile"]["roles"]["camera"] == "hung-camera"
        assert state["profile"]["path"] == str(loaded) and state["profile"]["views"] == 2
        controller.connect()
        snap = controller.snap()  # the new worker drives the (no longer hanging) camera
        assert snap["width"] > 0 and Path(snap["path"]).is_file()


def _catch(fn, into):
    try:
        fn()
    except Exception as exc:  # the request fails when its worker is ended
        into.append(exc)



def test_an_abort_ends_a_hung_worker_within_its_bound_and_a_new_one_takes_over(hung_rig,
                                                                               tmp_path):
    """An abort while the worker hangs (a watcher's is refused: aborting is the controller's;
    it takes control, as an operator at another terminal would): the hung worker is ended
    ``abort_bound_s`` after it, the run is marked, and a new worker serves the same profile;
    the server goes on."""
    with _hung_scan(hung_rig, tmp_path, "hung3") as (session, server, watcher, inbox, run_dir,
                                                     _):
        first_pid = session.pid
        hung_rig[1].unlink()  # the new worker's camera works
        with pytest.raises(ServerError, match="control"):
            watcher.abort()
        watcher.take_control()  # answered by the server while the worker hangs
        watcher.abort()
        finished = inbox.wait_for(lambda m: m.get("type") == "event"
                                  and m["event"]["event"] == "ScanFinished", timeout=120)
        assert finished["event"]["status"] == "aborted"
        assert "did not end its scan within 3 s of the abort" in finished["event"]["reason"]
        state = inbox.wait_for(lambda m: m.get("type") == "state"
                               and _worker(m).get("restarts") == 1
                               and _worker(m).get("state") == "running"
                               and m["state"]["profile"] is not None, timeout=120)["state"]
        assert state["session"] == "idle" and state["run"]["status"] == "aborted"
        assert not _pid_alive(first_pid) and session.pid != first_pid
        assert json.loads((run_dir / "manifest.json").read_text())["status"] == "aborted"
        watcher.take_control()
        watcher.connect()
        assert watcher.snap()["width"] > 0


def test_the_console_runs_in_the_worker(tmp_path, user_dirs):
    """input(), interrupts, completion and the history file, served from the worker; the
    console's namespace is the worker's session (its pid is not the server's)."""
    from dotshell.runtime.paths import history_path
    from dotshell.server.repl import read_history

    session = WorkerSession(write_test_profile(tmp_path, views=2), out_dir=tmp_path / "runs",
                            history_file=history_path())
    with served(session, name="console") as server:
        tui = attach(server)
        inbox = Inbox(tui)
        tui.console_run("import os\nanswer = input('angle? ')\nconnect(); "
                        "print(os.getpid(), move_to(float(answer)))")
        assert inbox.wait_for(lambda m: m.get("type") == "console_input")["prompt"] == "angle? "
        assert tui.console_reply("45")["delivered"]
        assert inbox.wait_for(lambda m: m.get("type") == "console_done")["ok"]
        out = "".join(m["text"] for m in inbox.of("console") if m["kind"] == "out")
        assert f"angle? 45\n{session.pid} 45.0\n" in out and session.pid != os.getpid()
        tui.console_run("input('more? ')")
        inbox.wait_for(lambda m: m.get("type") == "console_input" and m["prompt"] == "more? ")
        assert tui.console_interrupt()["interrupted"]
        assert not inbox.wait_for(lambda m: m.get("type") == "console_done"
                                  and len(inbox.of("console_done")) == 2)["ok"]
        assert "move_to(" in tui.complete("x = mov")["matches"]
        assert tui.refresh()["state"]["connected"] is True
    assert read_history(history_path())[-1] == "input('more? ')"


def test_a_worker_that_dies_mid_scan_is_replaced_and_its_run_marked(tmp_path, user_dirs):
    """A driver's crash (the worker killed) fails nothing in the server: the run is marked
    ``aborted`` with the exit named, and a new worker serves the profile."""
    session = WorkerSession(write_test_profile(tmp_path, views=3), out_dir=tmp_path / "runs")
    first_pid = session.pid
    with served(session, name="dies", poll_s=0.1) as server:
        tui = attach(server)
        inbox = Inbox(tui)
        run_dir = Path(tui.scan()["run_dir"])
        _wait_until(lambda: _frames_on_disk(run_dir) >= 1)
        os.kill(first_pid, 9)
        finished = inbox.wait_for(lambda m: m.get("type") == "event"
                                  and m["event"]["event"] == "ScanFinished", timeout=120)
        assert finished["event"]["status"] == "aborted"
        assert "exited unexpectedly (exit code -9)" in finished["event"]["reason"]
        inbox.wait_for(lambda m: m.get("type") == "state" and _worker(m).get("restarts") == 1
                       and _worker(m).get("state") == "running", timeout=120)
        manifest = json.loads((run_dir / "manifest.json").read_text())
        store = RunStore.open(run_dir)
        assert manifest["status"] == "aborted" and sum(v["frames"] for v in manifest["views"]) \
            == sum(store.frames(v["index"]).count() for v in manifest["views"]) >= 1
        tui.connect()
        assert tui.snap()["width"] > 0 and session.pid != first_pid


def test_the_tui_keeps_drawing_the_server_while_the_driver_hangs(hung_rig, tmp_path):
    """``dotshell tui`` on a pseudo-terminal, its server started by it (the worker loads the
    hung camera): the scan starts from the TUI's Scan tab, the camera hangs in C, and the TUI
    goes on drawing what the server pushes — the hung call named in its Log tab, then the
    scan ``aborted`` after ``dotshell stop --abort`` (the worker ended after its bound)."""
    from test_tui_pty import PtyScreen, stop_server, tui_command

    prof, flag = hung_rig
    sock = socket_path(server_name(prof))
    term = PtyScreen(tui_command(prof, tmp_path), tmp_path)
    try:
        term.wait_for("hung-camera")
        term.child.send("2")
        term.wait_for("s start")
        term.child.send("s")
        term.wait_for(re.compile(r"frames.* [1-9]\d*/\d+"))
        run_dir = Path(RemoteSession(sock, "test").refresh()["tracker"]["run_dir"])
        _wait_until(lambda: _frames_on_disk(run_dir) >= 1)
        flag.touch()
        term.child.send("4")  # the Log tab: the server's lines as they come
        term.wait_for("has not answered", timeout_s=120)
        term.wait_for("capture()", timeout_s=30)
        stopped = subprocess.run([sys.executable, "-m", "dotshell.cli.app", "stop", str(prof),
                                  "--abort"], capture_output=True, text=True, timeout=300)
        assert stopped.returncode == 0, stopped.stdout + stopped.stderr
        term.wait_exit(timeout_s=120)  # the server said bye: the TUI leaves
    finally:
        if term.child.isalive():
            term.child.terminate(force=True)
        stop_server(sock)
    manifest = json.loads((run_dir / "manifest.json").read_text())
    assert manifest["status"] == "aborted" and "camera (hung-camera) capture()" in \
        manifest["reason"]


def test_serve_reports_the_workers_profile_error_as_its_own(tmp_path, user_dirs):
    """The profile is loaded in the worker; a bad one still fails ``dotshell serve`` with the
    profile's own message and exit code 2, no traceback (the worker's reply came before its
    exit, and its end must not replace it)."""
    bad = tmp_path / "bad.toml"
    bad.write_text('[scan]\nviews = "x"\n')
    served_bad = subprocess.run([sys.executable, "-m", "dotshell.cli.app", "serve", str(bad), "--out",
                                 str(tmp_path / "runs"), "--socket",
                                 str(socket_path("bad"))], capture_output=True, text=True,
                                timeout=300)
    assert served_bad.returncode == 2
    assert f"{bad}: missing required key [profile]" in served_bad.stderr
    assert "Traceback" not in served_bad.stderr + served_bad.stdout
