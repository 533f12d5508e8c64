"""The server's side of the session worker (:mod:`dotshell.server.worker`): starts it, mirrors
what clients are shown, forwards requests, watches that it answers, ends and restarts it.

:class:`WorkerSession` stands where the server holds a :class:`~dotshell.session.console.Session`:
the same ``bus`` (events re-emitted as the worker sends them), ``state``, ``scanning``,
``connected``, ``run``, ``devices()``, ``stop()`` and ``close()``, read from the mirror the
worker keeps current, so the server answers its clients whatever the worker does.

The watch: the server pings the worker every :data:`PING_S`. A worker that has not answered
for :data:`HANG_S` is **hung**: the server reads the call board (which device call it is
inside, :mod:`dotshell.server.callboard`), logs it and shows it in the state (``worker``).
After an ``abort`` or ``stop`` (also ``dotshell stop --abort``) a hung worker gets
:data:`ABORT_BOUND_S` to end its scan; then the server **ends** it (SIGKILL: a process stuck
in C holding the GIL runs no signal handler), marks its run ``aborted`` with the hung call as
the reason (every frame already written kept and counted), and starts a new worker on the
same profile (rig not connected). ``restart_worker`` does the same on request.
"""

from __future__ import annotations

import itertools
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Callable

from dotshell.session.console import Run
from dotshell.errors import DotshellError
from dotshell.events import EventBus, Message, ScanFinished, ScanStarted
from dotshell.server.callboard import CallBoard
from dotshell.run.layout import RunLayout
from dotshell.server.protocol import (ServerError, decode, encode, event_from_wire, raise_remote,
                                      read_lines)

#: How often the server pings the worker (seconds).
PING_S = 0.5
#: A worker silent this long (seconds) is hung: its device call is named in the log and state.
HANG_S = 5.0
#: After abort or stop, a hung worker is ended this long (seconds) after the request.
ABORT_BOUND_S = 10.0
#: How long ``close`` waits for the worker to close the rig before it is ended (seconds).
CLOSE_BOUND_S = 60.0
#: How long a new worker may take to load its plugins and profile (seconds).
START_TIMEOUT_S = 120.0


class WorkerGone(ServerError):
    """The session worker was ended (or died) while a request was under way."""


class _Pending:
    def __init__(self) -> None:
        self.done = threading.Event()
        self.reply: dict[str, Any] | None = None


class WorkerConsole:
    """What the server reads of the console that runs in the worker."""

    def __init__(self, owner: WorkerSession) -> None:
        from dotshell.server.repl import Transcript

        self._owner = owner
        #: the worker's console messages, kept here so that a front end attaching later (also
        #: after the worker was restarted) is shown them; see :class:`ServerConsole`'s lock
        self.kept = Transcript()
        self.lock = self.kept.lock

    def transcript(self) -> list[dict[str, Any]]:
        return self.kept.messages()

    @property
    def history(self) -> list[str]:
        return list(self._owner.mirror.get("history") or [])

    @property
    def busy(self) -> bool:
        return bool((self._owner.mirror.get("console") or {}).get("busy"))

    @property
    def waiting_prompt(self) -> str | None:
        return (self._owner.mirror.get("console") or {}).get("prompt")

    def interrupt(self) -> bool:
        self._owner.send("console_interrupt", {})
        return True


class WorkerSession:
    """A session held by a worker process (see the module docstring).

    Args:
        profile: the profile file to load (None: load one later).
        out_dir: parent directory of runs.
        overrides: ``KEY=VALUE`` profile overrides.
        strict_plugins: a plugin that fails to load is an error.
        history_file: the console history (None: not kept).
        hang_s, abort_bound_s: see :data:`HANG_S` and :data:`ABORT_BOUND_S` (seconds).
    """

    def __init__(self, profile: str | Path | None = None, *, out_dir: str | Path = "runs",
                 overrides: list[str] | tuple[str, ...] = (), strict_plugins: bool = False,
                 history_file: Path | None = None, hang_s: float = HANG_S,
                 abort_bound_s: float = ABORT_BOUND_S) -> None:
        self.bus = EventBus()
        self.console = WorkerConsole(self)
        self.profile_path = Path(profile).resolve() if profile else None
        self.overrides = list(overrides)
        self.out_dir = Path(out_dir)
        self.strict_plugins = strict_plugins
        self.history_file = history_file
        self.hang_s, self.abort_bound_s = hang_s, abort_bound_s
        self.mirror: dict[str, Any] = {}
        self.job = None  # the server waits on no thread of ours
        #: ``push(message)`` for every console message; ``changed()`` when the mirror changes.
        self.on_push: Callable[[dict[str, Any]], None] = lambda m: None
        self.on_change: Callable[[], None] = lambda: None
        self.restarts = 0
        self.ended: str = ""  # why the last worker was ended ("" if none was)
        self.hung: str = ""  # the calls a hung worker is inside ("" while it answers)
        self._ids = itertools.count(1)
        self._send_lock = threading.Lock()
        self._life = threading.RLock()  # one end or start of the worker at a time
        self._ready = threading.Event()  # a worker is up and has loaded its profile
        self._pinged = 0.0  # when the last ping went out (monotonic s)
        self._pending: dict[Any, _Pending] = {}
        self._lock = threading.RLock()
        self._scan_run: str | None = None  # the run of the scan under way (from its events)
        self._last_run: str | None = None
        self._last_heard = time.monotonic()
        self._closing = False
        self._abort_at: float | None = None
        self._abort_request = "abort"  # the request that armed _abort_at: abort or stop
        self._proc: subprocess.Popen[bytes] | None = None
        self._sock: socket.socket | None = None
        self._board: CallBoard | None = None
        self._start()
        threading.Thread(target=self._watch, daemon=True, name="dotshell-worker-watch").start()

    # ---- the session as the server reads it -----------------------------------------------------

    @property
    def state(self) -> str:
        return str(self.mirror.get("state", "idle"))

    @property
    def scanning(self) -> bool:
        return self.state != "idle"

    @property
    def connected(self) -> bool:
        return bool(self.mirror.get("connected"))

    @property
    def projected(self) -> str | None:
        return self.mirror.get("projected")

    @property
    def run(self) -> Run | None:
        """The session's last run (also one of a worker since ended)."""
        run_dir = (self.mirror.get("run") or {}).get("dir") or self._last_run
        return Run(run_dir) if run_dir else None

    @property
    def summary(self) -> dict[str, Any] | None:
        """The profile as front ends show it (:func:`dotshell.server.commands.profile_summary`)."""
        return self.mirror.get("profile")

    @property
    def profile(self) -> Any:
        summary = self.summary
        return SimpleNamespace(**summary) if summary else None

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    def devices(self) -> list[dict[str, Any]]:
        return list(self.mirror.get("rows") or [])

    def describe(self) -> dict[str, Any]:
        """The ``worker`` entry of the server's state."""
        silent = int(time.monotonic() - self._last_heard) if self.hung else 0
        state = "hung" if self.hung else "running" if self._ready.is_set() else "starting"
        return {"pid": self.pid, "state": state,
                "hung": self.hung, "silent_s": silent, "restarts": self.restarts,
                "ended": self.ended,
                "hang_s": self.hang_s, "abort_bound_s": self.abort_bound_s}

    # ---- requests -----------------------------------------------------------------------------

    def send(self, cmd: str, args: dict[str, Any], rid: Any = None) -> None:
        """Send a request without waiting for its reply."""
        sock = self._sock
        if sock is None:
            raise WorkerGone("the session worker is restarting; try again in a moment.")
        try:
            with self._send_lock:
                sock.sendall(encode({"id": rid, "cmd": cmd, "args": args}))
        except OSError as exc:
            raise WorkerGone(f"the session worker is gone ({exc}); the server restarts it.") \
                from None

    def request(self, cmd: str, args: dict[str, Any], timeout: float | None = None) -> Any:
        """Run a session request in the worker and return its result (its error re-raised).
        A request under way when the worker is ended fails with :class:`WorkerGone`."""
        if cmd in ("abort", "stop"):
            getattr(self, cmd)()
            return None
        if not self._closing and not self._ready.wait(START_TIMEOUT_S):
            raise WorkerGone("the session worker is not running (it could not be restarted: "
                             "see the server log); stop the server and start it again.")
        rid = next(self._ids)
        pending = _Pending()
        with self._lock:
            self._pending[rid] = pending
        try:
            self.send(cmd, args, rid)
            if not pending.done.wait(timeout):
                raise ServerError(f"the session worker did not answer {cmd} within {timeout:g} s.")
        finally:
            with self._lock:
                self._pending.pop(rid, None)
        reply = pending.reply
        assert reply is not None
        if reply.get("type") == "gone":
            raise WorkerGone(reply["error"])
        if not reply.get("ok"):
            raise_remote(reply)
        return reply.get("result")

    def abort(self) -> None:
        """Ask the worker to abort its scan; a hung worker is ended after ``abort_bound_s``."""
        self._arm_abort("abort")
        self._send_quietly("abort")

    def stop(self) -> None:
        """Stop every moving device and abort the scan; as :meth:`abort` when hung."""
        self._arm_abort("stop")
        self._send_quietly("stop")

    def _send_quietly(self, cmd: str) -> None:
        try:
            self.send(cmd, {})
        except WorkerGone:
            pass  # nothing runs in a worker that is being replaced

    def _arm_abort(self, request: str) -> None:
        if self.scanning and self._abort_at is None:
            self._abort_at = time.monotonic() + self.abort_bound_s
            self._abort_request = request

    def close(self) -> None:
        """Abort a scan, close the rig and end the worker: by force when it does not answer
        within :data:`CLOSE_BOUND_S`, or is hung ``abort_bound_s`` after the request."""
        self._closing = True
        self.stop()
        pending = _Pending()
        with self._lock:
            self._pending["close"] = pending
        t0 = time.monotonic()
        try:
            self.send("close", {}, rid="close")
            while not pending.done.wait(PING_S):
                waited = time.monotonic() - t0
                if self.hung and waited >= self.abort_bound_s:
                    self._end(f"it did not end its scan within {self.abort_bound_s:g} s of the "
                              "stop")
                    return
                if waited > CLOSE_BOUND_S:
                    self._end(f"it did not close the rig within {CLOSE_BOUND_S:g} s")
                    return
        except WorkerGone:
            pass
        with self._life:  # the watch may be ending it: its run is marked and said before bye
            proc = self._proc
            if proc is not None:
                try:
                    proc.wait(10)
                except subprocess.TimeoutExpired:
                    self._end("it did not exit after closing the rig")
            self._release()

    def restart(self, reason: str = "restart requested") -> int:
        """End the worker (its scan aborted and its run marked) and start a new one on the
        same profile; returns the new worker's pid."""
        with self._life:
            self._end(reason)
            self.restarts += 1
            self._start()
        self.on_change()
        return self.pid or 0

    # ---- the process --------------------------------------------------------------------------

    def _start(self) -> None:
        loaded = self.mirror.get("profile_path")  # the profile the last worker had loaded
        if loaded and (self.profile_path is None or Path(loaded) != self.profile_path):
            self.profile_path, self.overrides = Path(loaded), []
        board = CallBoard()
        mine, theirs = socket.socketpair()
        spec = {"sock_fd": theirs.fileno(), "board_fd": board.fd,
                "profile": str(self.profile_path) if self.profile_path else None,
                "out": str(self.out_dir), "overrides": self.overrides,
                "strict_plugins": self.strict_plugins,
                "history": str(self.history_file) if self.history_file else None}
        # its own session: a terminal's ctrl+c reaches the server, which closes the worker
        proc = subprocess.Popen([sys.executable, "-m", "dotshell.server.worker", json.dumps(spec)],
                                pass_fds=(theirs.fileno(), board.fd), stdin=subprocess.DEVNULL,
                                start_new_session=True)
        theirs.close()
        ready = _Pending()
        with self._lock:
            self._pending["ready"] = ready
            self._proc, self._sock, self._board = proc, mine, board
            self.mirror, self.hung, self._last_heard = {}, "", time.monotonic()
        threading.Thread(target=self._read, args=(mine, proc), daemon=True,
                         name="dotshell-worker-read").start()
        ready.done.wait(START_TIMEOUT_S)
        with self._lock:
            self._pending.pop("ready", None)
        if ready.reply is None:
            self._end(f"it did not load its profile within {START_TIMEOUT_S:g} s")
            raise ServerError(f"the session worker did not start within {START_TIMEOUT_S:g} s.")
        if ready.reply.get("type") == "gone":
            raise ServerError(f"the session worker exited before it was ready "
                              f"(exit code {proc.poll()}); see the server's output.")
        if not ready.reply.get("ok", True):
            proc.wait(10)
            self._release()
            raise_remote(ready.reply)
        self._ready.set()

    def _read(self, sock: socket.socket, proc: subprocess.Popen[bytes]) -> None:
        try:
            for line in read_lines(sock):
                self._last_heard = time.monotonic()
                if self.hung:
                    self._answers_again()
                self._receive(decode(line))
        except (OSError, DotshellError):
            pass
        self._gone(proc, f"the session worker (pid {proc.pid}) ended")

    def _receive(self, m: dict[str, Any]) -> None:
        kind = m.get("type")
        if kind == "mirror":
            self.mirror = m["mirror"]
            if self.mirror.get("run"):
                self._last_run = self.mirror["run"]["dir"]
            self.on_change()
        elif kind == "event":
            ev = event_from_wire(m["event"])
            if isinstance(ev, ScanStarted):
                self._scan_run = ev.run_dir
            elif isinstance(ev, ScanFinished):
                self._scan_run, self._abort_at = None, None
            self.bus.emit(ev)
        elif kind == "push":
            with self.console.lock:  # kept and sent at once (a greeting sees it once)
                self.console.kept.add(m["message"])
                self.on_push(m["message"])
        elif kind in ("reply", "ready"):
            rid = "ready" if kind == "ready" else m.get("id")
            with self._lock:
                pending = self._pending.pop(rid, None)
            if pending is not None:
                pending.reply = m
                pending.done.set()

    def _gone(self, proc: subprocess.Popen[bytes], why: str) -> None:
        """The worker's connection closed: fail every request still waiting."""
        with self._lock:
            if self._proc is not proc:
                return
            pending, self._pending = list(self._pending.values()), {}
        for p in pending:
            if not p.done.is_set():  # a reply that came before the end stands
                p.reply = {"type": "gone", "error": f"{why}; the request did not finish."}
                p.done.set()

    def _release(self) -> None:
        with self._lock:
            sock, board = self._sock, self._board
            self._sock = self._board = None
        if sock is not None:
            sock.close()
        if board is not None:
            board.close()

    # ---- the watch: pings, hangs, ending a hung worker ----------------------------------------

    def _watch(self) -> None:
        while True:
            time.sleep(PING_S)
            proc = self._proc
            if proc is None or (self._closing and self._sock is None):
                return
            if self._last_heard >= self._pinged:  # one ping at a time: a hung worker's buffer
                try:                                # never fills
                    self._pinged = time.monotonic()
                    self.send("ping", {}, rid="ping")
                except WorkerGone:
                    continue
            silent = time.monotonic() - self._last_heard
            if silent >= self.hang_s and not self.hung and proc.poll() is None:
                self._hangs(silent)
            with self._life:
                if proc is not self._proc:  # restarted meanwhile
                    continue
                if self._abort_at is not None and time.monotonic() >= self._abort_at:
                    if self.hung:
                        self._end(f"it did not end its scan within {self.abort_bound_s:g} s of "
                                  f"the {self._abort_request}")
                        if not self._closing:
                            self._start_again()
                        continue
                    self._abort_at = None if not self.scanning else self._abort_at
                if proc.poll() is not None and not self._closing and self._sock is not None:
                    self._end(f"it exited unexpectedly (exit code {proc.returncode})")
                    self._start_again()

    def _hangs(self, silent_s: float) -> None:
        board = self._board
        calls = board.describe(self.pid) if board is not None else ""
        self.hung = calls or "no device call (Python or C code of its own)"
        self.bus.emit(Message(level="error", text=(
            f"the session worker (pid {self.pid}) has not answered for {silent_s:.0f} s; it is "
            f"inside {self.hung}. The server and its clients go on: abort or stop the scan (it "
            f"is ended {self.abort_bound_s:g} s later if still hung; frames are kept), or "
            "restart the worker (dotshell stop --restart-worker).")))
        self.on_change()

    def _answers_again(self) -> None:
        self.hung = ""
        self.bus.emit(Message(level="info", text="the session worker answers again"))
        self.on_change()

    def _end(self, why: str) -> None:
        """End the worker by force (when it is alive), mark the run of its scan, fail its
        requests; the caller starts a new one if wanted."""
        with self._life:
            self._end_now(why)

    def _end_now(self, why: str) -> None:
        with self._lock:
            proc, run_dir, board = self._proc, self._scan_run, self._board
        if proc is None or (self._sock is None and proc.poll() is not None):
            return  # ended already
        calls = board.describe(proc.pid) if board is not None else ""
        self._ready.clear()
        reason = (f"the session worker (pid {proc.pid}) was ended: {why}"
                  + (f"; it was inside {calls}" if calls else ""))
        self._gone(proc, reason)  # its requests fail with the reason, not just "ended"
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)  # stuck in C holding the GIL: nothing else works
            proc.wait()
        self.ended, self.hung, self._abort_at, self._scan_run = reason, "", None, None
        self._release()
        self.bus.emit(Message(level="error", text=reason))
        if run_dir is not None:
            self._close_run(Path(run_dir), reason)
        self.mirror = {**self.mirror, "state": "idle", "connected": False, "projected": None,
                       "console": {"busy": False, "prompt": None},
                       "rows": [{**r, "connected": False} for r in self.mirror.get("rows", [])]}
        self.on_change()

    def _close_run(self, run_dir: Path, reason: str) -> None:
        self._last_run = str(run_dir)
        try:
            status, summary = mark_run_aborted(run_dir, reason)
        except DotshellError as exc:
            self.bus.emit(Message(level="error", text=f"{run_dir} could not be marked: {exc}"))
            status, summary = "interrupted", {}
        self.bus.emit(ScanFinished(status=status, run_dir=str(run_dir), summary=summary,
                                   reason=reason))

    def _start_again(self) -> None:
        self.restarts += 1
        try:
            self._start()
        except DotshellError as exc:
            self.bus.emit(Message(level="error", text=f"the session worker could not be "
                                  f"restarted: {exc}"))
        self.on_change()


def mark_run_aborted(run_dir: Path, reason: str) -> tuple[str, dict[str, Any]]:
    """Record the truth of a run whose scan process was ended: status ``aborted`` with
    ``reason``, each view's frame count as found on disk (a stack cut short reads up to its
    last complete page), and a ``ScanFinished`` line in ``events.jsonl``. Returns (status,
    summary: ``frames`` on disk)."""
    from dotshell.run.lifecycle import RunLock
    from dotshell.run.store import RunStore

    store = RunStore.open(run_dir)
    with RunLock(run_dir) as lock:
        lock.acquire("serve (closing the run of an ended session worker)")
        m = store.manifest
        if m.get("status") != "running":  # the worker finished it before it was ended
            return str(m.get("status")), {}
        total = 0
        for v in m["views"]:
            try:
                n = store.frames(v["index"]).count()
            except DotshellError:
                n = 0
            v["frames"] = n
            total += n
        m.update(status="aborted", reason=reason)
        store.write_json(RunLayout.MANIFEST, m)
        finished = ScanFinished(status="aborted", run_dir=str(run_dir),
                                summary={"frames": total}, reason=reason)
        store.append_event(finished.to_dict())
    return "aborted", {"frames": total}
