"""The rig server process: one session on a Unix-domain socket — held by a session worker
process (:mod:`dotshell.server.supervisor`, what ``dotshell serve`` runs) or, for tests and
embedding, a :class:`~dotshell.session.console.Session` in this process.

Threads: the caller's (accepts clients, takes signals), one poller (device status and session
state for attached clients, idle exit), and per client a reader (requests in; urgent ones such
as ``abort`` answered at once), a worker (the client's other requests, one at a time, in order)
and a writer (messages out from a bounded queue, so a stalled terminal never blocks a scan).

Every event of the session's bus is logged to ``server.log`` in the server's state directory
(and, while a scan runs, to ``server.log`` in its run directory) and sent to every client.
SIGTERM and SIGINT stop the server cleanly: the scan is aborted (frames kept, run ``aborted``),
every device that can move is stopped, the rig is closed. SIGHUP does the same unless
``on_hangup`` is ``keep``.
"""

from __future__ import annotations

import os
import queue
import select
import selectors
import signal
import socket
import struct
import sys
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any, TextIO

from dotshell import __version__
from dotshell.session.console import Session
from dotshell.errors import DotshellError
from dotshell.events import Event, ScanFinished, ScanPaused, ScanResumed, ScanStarted
from dotshell.server.commands import COMMANDS, Context, profile_summary
from dotshell.server.describe import describe_event
from dotshell.runtime.paths import HANGUP_CHOICES, open_private
from dotshell.server.progress import ScanTracker
from dotshell.server.protocol import (CONTROL_COMMANDS, PROTOCOL_VERSION, URGENT_COMMANDS,
                                      ServerError, decode, encode, error_reply, peer_uid,
                                      read_lines)
from dotshell.server.repl import ServerConsole
from dotshell.server.supervisor import WorkerSession

#: Messages waiting for one client before it is dropped as stalled.
OUTBOX_SIZE = 50000
#: Events a newly attached client receives for its log.
BACKLOG_SIZE = 1000
#: With ``exit_when_idle``: seconds without a client and without a scan before the server exits.
IDLE_GRACE_S = 10.0
#: After a refused (oversized) line: what the server still reads and drops of the rest before it
#: closes (bytes, seconds), so that the peer can read the error reply: closing a socket with
#: unread input resets the connection, and the peer's sendall or recv then fails without it.
DISCARD_BYTES = 64 * 1024 * 1024
DISCARD_S = 2.0
SERVER_COMMANDS = ("hello", "state", "control", "release", "shutdown", "bye", "restart_worker")
LIFECYCLE = (ScanStarted, ScanFinished, ScanPaused, ScanResumed)


def _peer(sock: socket.socket) -> tuple[int, int]:
    """(pid, uid) of the process at the other end of a Unix socket (Linux SO_PEERCRED)."""
    pid, _, _ = struct.unpack("3i", sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED,
                                                    struct.calcsize("3i")))
    return pid, peer_uid(sock)


class Connection:
    """One attached client."""

    def __init__(self, server: RigServer, sock: socket.socket, cid: int, pid: int) -> None:
        self.server = server
        self.sock = sock
        self.id = cid
        self.info: dict[str, Any] = {"client": "?", "pid": pid, "tty": None}
        self.greeted = False
        self.outbox: queue.Queue[bytes | None] = queue.Queue(maxsize=OUTBOX_SIZE)
        self.requests: queue.Queue[dict[str, Any] | None] = queue.Queue()
        self.closed = threading.Event()
        self._threads = [threading.Thread(target=fn, daemon=True, name=f"dotshell-client-{cid}-{n}")
                         for n, fn in (("read", self._read), ("work", self._work),
                                       ("write", self._write))]

    def start(self) -> None:
        for t in self._threads:
            t.start()

    def describe(self) -> str:
        tty = f" on {self.info['tty']}" if self.info.get("tty") else ""
        return f"{self.info['client']}#{self.id} (pid {self.info['pid']}{tty})"

    def public(self) -> dict[str, Any]:
        return {"id": self.id, **self.info}

    # ---- out -------------------------------------------------------------------------------------

    def send_bytes(self, data: bytes) -> None:
        if self.closed.is_set():
            return
        try:
            self.outbox.put_nowait(data)
        except queue.Full:
            self.close("it stopped reading its messages")

    def send(self, message: dict[str, Any]) -> None:
        self.send_bytes(encode(message))

    def flushed(self, timeout_s: float) -> bool:
        """Wait (at most ``timeout_s``) until the messages queued before :meth:`close` are
        written to the socket; False if the client did not take them in time."""
        writer = self._threads[2]
        if writer.is_alive() and writer is not threading.current_thread():
            writer.join(timeout_s)
        return not writer.is_alive()

    def _write(self) -> None:
        while True:
            data = self.outbox.get()
            if data is None:
                break
            try:
                self.sock.sendall(data)
            except OSError:
                break
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.close("disconnected")

    # ---- in --------------------------------------------------------------------------------------

    def _read(self) -> None:
        reason = "disconnected"
        try:
            for line in read_lines(self.sock, self.closed):
                self._dispatch(line)
        except ServerError as exc:
            self.send(error_reply(None, exc))
            self._discard_input()
        except OSError:
            pass
        except Exception as exc:  # whatever a line does, the connection ends cleanly
            self.send(error_reply(None, exc))
            reason = f"its request failed ({type(exc).__name__}: {exc})"
        self.close(reason)

    def _discard_input(self) -> None:
        """Read and drop what the peer still sends, up to :data:`DISCARD_BYTES` or
        :data:`DISCARD_S` seconds (bounded in time and memory), or until it stops sending."""
        deadline, left = time.monotonic() + DISCARD_S, DISCARD_BYTES
        while left > 0:
            wait = deadline - time.monotonic()
            if wait <= 0 or not select.select([self.sock], [], [], wait)[0]:
                return
            try:
                data = self.sock.recv(65536)
            except OSError:
                return
            if not data:
                return
            left -= len(data)

    def _dispatch(self, line: bytes) -> None:
        try:
            message = decode(line)
        except ServerError as exc:
            self.send(error_reply(None, exc))
            return
        if message.get("cmd") in URGENT_COMMANDS:
            self.server.handle(self, message)
        else:
            self.requests.put(message)

    def _work(self) -> None:
        while True:
            message = self.requests.get()
            if message is None:
                return
            self.server.handle(self, message)

    def close(self, reason: str) -> None:
        """Stop serving this client; pending messages are still sent, then the socket closes."""
        if self.closed.is_set():
            return
        self.closed.set()
        self.requests.put(None)
        while True:
            try:
                self.outbox.put_nowait(None)
                break
            except queue.Full:
                try:
                    self.outbox.get_nowait()
                except queue.Empty:
                    pass
        self.server.detach(self, reason)


class RigServer:
    """Serves ``session`` on ``socket_path``.

    Args:
        session: the session every client shares (the server closes it when it stops): a
            :class:`~dotshell.server.supervisor.WorkerSession` (what ``dotshell serve`` runs: the
            session in a worker process, so a driver hung in C stops only that process) or a
            :class:`Session` in this process (tests, embedding).
        socket_path: where to listen (its directory must be private to the user).
        name: shown by ``dotshell status``.
        log_dir: where ``server.log`` goes.
        on_hangup: ``abort`` (SIGHUP stops the scan and the server) or ``keep`` (ignored).
        exit_when_idle: exit once no client is attached and no scan runs (servers a front end
            started for itself).
        history_file: the console history (None: not kept).
        poll_s: how often device status is read for attached clients (seconds).
        echo: also write log lines to stderr (a server in the foreground).
    """

    def __init__(self, session: Session | WorkerSession, socket_path: Path, *, name: str, log_dir: Path,
                 on_hangup: str = "abort", exit_when_idle: bool = False,
                 history_file: Path | None = None, poll_s: float = 0.5,
                 echo: bool = False) -> None:
        if on_hangup not in HANGUP_CHOICES:
            raise DotshellError(f"on_hangup {on_hangup!r}: choose one of {', '.join(HANGUP_CHOICES)}.")
        self.session = session
        self.socket_path = Path(socket_path)
        self.name = name
        self.on_hangup = on_hangup
        self.exit_when_idle = exit_when_idle
        self.poll_s = poll_s
        self.echo = echo
        self.started = time.time()
        self.log_path = Path(log_dir) / "server.log"
        self.tracker = ScanTracker()
        self.backlog: deque[dict[str, Any]] = deque(maxlen=BACKLOG_SIZE)
        self.clients: list[Connection] = []
        self.controller: Connection | None = None
        self.worker = session if isinstance(session, WorkerSession) else None
        self.console: Any = (session.console if isinstance(session, WorkerSession)
                             else ServerConsole(session, self.broadcast, history_file))
        self.context = Context(session, self.console)  # type: ignore[arg-type]
        self._clients_lock = threading.RLock()
        # held while a client is greeted and while events, states and device rows are pushed: an
        # attaching client gets each of them exactly once, and never after a newer one
        self._event_lock = threading.RLock()
        self._log_lock = threading.RLock()
        self._log: TextIO = open_private(self.log_path)
        self._run_log: TextIO | None = None
        self._next_id = 1
        self._last_state: dict[str, Any] | None = None
        self._last_rows: Any = None
        self._last_activity = time.monotonic()
        self._signals: list[int] = []
        self._stopping = threading.Event()
        self._done = threading.Event()
        self.exit_reason = ""
        self._wake_r, self._wake_w = os.pipe()
        self._listener: socket.socket | None = None
        self._unsubscribe = session.bus.subscribe(self._on_event)
        if self.worker is not None:
            self.worker.on_push = self.broadcast
            self.worker.on_change = self._on_worker_change

    # ---- lifetime ----------------------------------------------------------------------------

    def start(self) -> None:
        """Listen on the socket (0600) and start polling; clients are accepted by
        :meth:`serve_forever`."""
        path = self.socket_path
        self._claim(path)
        if path.exists() or path.is_symlink():
            path.unlink()  # stale: a server on it would hold the lock
        listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        listener.bind(os.fspath(path))
        os.chmod(path, 0o600)
        listener.listen(16)
        self._listener = listener
        self.log(f"dotshell {__version__} server {self.name} (pid {os.getpid()}) listening on "
                 f"{path}; profile {self.session.profile.name if self.session.profile else 'none'}; "
                 f"out {self.session.out_dir.resolve()}; on_hangup {self.on_hangup}"
                 + ("; exits when idle" if self.exit_when_idle else ""))
        threading.Thread(target=self._poll, daemon=True, name="dotshell-poller").start()

    def _claim(self, path: Path) -> None:
        """Hold the server lock of ``path`` (one server per socket, so per profile, even while
        a server is momentarily unresponsive); refused naming the holder."""
        from dotshell.rig.owners import held_devices, profile_device_ids
        from dotshell.runtime.locks import OwnerLock, describe, profile_identity, server_lock_path

        profile = self.session.profile
        self._owner = OwnerLock(server_lock_path(path))
        other = self._owner.acquire({"name": self.name, "socket": str(path),
                                     **profile_identity(profile.source if profile else None)})
        if other is not None:
            raise ServerError(f"a rig server already runs on {path}: {describe(other)}; see "
                              "dotshell status, or stop it with dotshell stop.")
        # In-process, the session's Profile; behind a worker, the summary it sent (device_ids)
        ids = (profile_device_ids(profile) if hasattr(profile, "role")
               else getattr(profile, "device_ids", None) or {})
        held = held_devices(ids)
        if held:
            self._owner.release()
            role, ident, info = held[0]
            raise ServerError(f"the profile's {role} ({ident}) is held by {describe(info)}; one "
                              "process drives a device at a time. Stop that scan or server "
                              "(dotshell stop PROFILE) first.")

    def serve_forever(self) -> int:
        """Accept clients until the server stops; installs the signal handlers when called
        from the main thread. Returns the exit code (0: a clean stop)."""
        if self._listener is None:
            self.start()
        if threading.current_thread() is threading.main_thread():
            for signum in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
                signal.signal(signum, self._on_signal)
        sel = selectors.DefaultSelector()
        sel.register(self._listener, selectors.EVENT_READ, "accept")  # type: ignore[arg-type]
        sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        try:
            while not self._done.is_set():
                for key, _ in sel.select():
                    if key.data == "accept":
                        self._accept()
                    else:
                        os.read(self._wake_r, 512)
                while self._signals:
                    self._handle_signal(self._signals.pop(0))
        finally:
            sel.close()
            self._close_listener()
        return 0

    def _wake(self) -> None:
        try:
            os.write(self._wake_w, b"x")
        except OSError:
            pass

    def _on_signal(self, signum: int, frame: Any) -> None:
        self._signals.append(signum)
        self._wake()

    def _handle_signal(self, signum: int) -> None:
        name = signal.Signals(signum).name
        if signum == signal.SIGHUP and self.on_hangup == "keep":
            self.log(f"{name}: kept running (on_hangup = keep)", "warning")
            return
        self.log(f"{name}: aborting any scan cleanly, stopping the devices, then exiting",
                 "warning")
        self.shutdown(name, abort=True)

    def shutdown(self, reason: str, abort: bool = True) -> None:
        """Stop the server in the background: abort the scan (``abort``; else refuse while one
        runs), stop the devices, close the rig, say ``bye`` to every client."""
        self._refuse_stop_during_scan(abort)
        if self._stopping.is_set():
            return
        self._stopping.set()
        threading.Thread(target=self._shutdown, args=(reason,), daemon=True,
                         name="dotshell-shutdown").start()

    def _refuse_stop_during_scan(self, abort: bool) -> None:
        if self.session.scanning and not abort:
            raise DotshellError(f"a scan is {self.session.state} ({self.tracker.views_done}/"
                                f"{self.tracker.n_views} views); stop it first, or stop the "
                                "server with dotshell stop --abort (frames are kept).")

    def _shutdown(self, reason: str) -> None:
        self.exit_reason = reason
        try:
            if self.worker is not None:  # the scan aborted, the rig closed; a hung worker ended
                self.worker.close()
            else:
                self.session.stop()
                self.console.interrupt()
                while self.session.scanning:  # the scan saves what it has (also a console's)
                    time.sleep(0.05)
                self.session.close()
        except Exception as exc:  # closing must go on whatever a device does
            self.log(f"while stopping: {type(exc).__name__}: {exc}", "error")
        self.log(f"server stopped ({reason})")
        self.broadcast({"type": "bye", "reason": reason})
        with self._clients_lock:
            clients = list(self.clients)
        for c in clients:
            c.close("the server stopped")
        for c in clients:  # bye is on its way before the process may end (daemon writers)
            c.flushed(timeout_s=5.0)
        self._unsubscribe()
        self._done.set()
        self._wake()

    def _close_listener(self) -> None:
        if self._listener is not None:
            self._listener.close()
            self._listener = None
            try:
                self.socket_path.unlink()
            except FileNotFoundError:
                pass
            self._owner.release()
        with self._log_lock:
            self._log.close()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until the server has stopped; False on timeout."""
        return self._done.wait(timeout)

    # ---- clients -----------------------------------------------------------------------------------

    def _accept(self) -> None:
        try:
            sock, _ = self._listener.accept()  # type: ignore[union-attr]
        except OSError:
            return
        pid, uid = _peer(sock)
        if uid != os.getuid() or self._stopping.is_set():
            sock.close()
            return
        with self._clients_lock:
            conn = Connection(self, sock, self._next_id, pid)
            self._next_id += 1
            self.clients.append(conn)
            self._last_activity = time.monotonic()
        conn.start()

    def detach(self, conn: Connection, reason: str) -> None:
        with self._clients_lock:
            if conn not in self.clients:
                return
            self.clients.remove(conn)
            if self.controller is conn:
                self.controller = None
            self._last_activity = time.monotonic()
        if conn.greeted:
            self.log(f"{conn.describe()} detached: {reason}")
        self.push_state()

    def broadcast(self, message: dict[str, Any]) -> None:
        data = encode(message)
        with self._clients_lock:
            clients = [c for c in self.clients if c.greeted]
        for c in clients:
            c.send_bytes(data)

    # ---- requests ----------------------------------------------------------------------------------

    def handle(self, conn: Connection, message: dict[str, Any]) -> None:
        rid, cmd = message.get("id"), message.get("cmd")
        args = {k: v for k, v in message.items() if k not in ("id", "cmd")}
        try:
            if cmd not in COMMANDS and cmd not in SERVER_COMMANDS:
                raise ServerError(f"unknown request {cmd!r} (protocol {PROTOCOL_VERSION}); the "
                                  "requests are listed in docs/server.md.")
            if not conn.greeted and cmd != "hello":
                raise ServerError("the first request must be hello (docs/server.md).")
            if cmd in CONTROL_COMMANDS:
                self._require_control(conn, cmd)
            if cmd not in ("state", "devices", "history", "complete", "patterns", "plugins"):
                self.log(f"{conn.describe()}: {cmd} {str(args)[:200] if args else ''}".rstrip(),
                         "debug")
            if cmd in ("hello", "shutdown"):
                getattr(self, f"_cmd_{cmd}")(conn, rid, args)  # they reply themselves
            elif cmd in SERVER_COMMANDS:
                result = getattr(self, f"_cmd_{cmd}")(conn, args)
                conn.send({"type": "reply", "id": rid, "ok": True, "result": result})
            elif self.worker is not None:  # what the mirror holds is answered while it hangs
                result = (self.worker.devices() if cmd == "devices" else
                          self.console.history if cmd == "history" else
                          self.worker.request(cmd, args))
                conn.send({"type": "reply", "id": rid, "ok": True, "result": result})
            else:
                result = COMMANDS[cmd](self.context, args)
                conn.send({"type": "reply", "id": rid, "ok": True, "result": result})
        except Exception as exc:  # the request failed; the server and the session live on
            conn.send(error_reply(rid, exc))
            if isinstance(exc, DotshellError):
                self.log(f"{conn.describe()}: {cmd} refused: {exc}", "warning")
            else:
                self.log(f"{conn.describe()}: {cmd} failed: {type(exc).__name__}: {exc}", "error")
        if cmd == "hello" and conn.greeted:
            self.log(f"{conn.describe()} attached"
                     + (" in control" if self.controller is conn else " watching"))
        if cmd not in ("state", "devices", "history", "complete", "patterns", "plugins"):
            self.push_state()

    def _require_control(self, conn: Connection, cmd: str) -> None:
        with self._clients_lock:
            if self.controller is None:
                self.controller = conn  # free: whoever acts first controls
            elif self.controller is not conn:
                raise ServerError(f"cannot {cmd}: {self.controller.describe()} controls the rig; "
                                  "watch, or take control (in the TUI: ctrl+t).")

    def _cmd_hello(self, conn: Connection, rid: Any, args: dict[str, Any]) -> None:
        """Greet a client: its reply (the state, the scan so far, recent events) is queued
        before any event that is not in it, so the client sees each event exactly once."""
        if args.get("protocol") != PROTOCOL_VERSION:
            raise ServerError(f"this server speaks protocol {PROTOCOL_VERSION} (dotshell "
                              f"{__version__}), the client {args.get('protocol')!r}; use the same "
                              "dotshell for both, or stop the server (dotshell stop).")
        conn.info.update(client=str(args.get("client", "client"))[:40],
                         tty=args.get("tty") or None)
        with self._clients_lock:
            if args.get("control") and self.controller is None:
                self.controller = conn
        with self.console.lock, self._event_lock:  # the console's transcript is whole too
            conn.greeted = True
            conn.send({"type": "reply", "id": rid, "ok": True, "result": {
                "you": conn.id, "state": self.state(), "tracker": self.tracker.to_dict(),
                "backlog": list(self.backlog), "history": self.console.history[-500:],
                "rows": self._last_rows, "console": self.console.transcript()}})

    def _cmd_state(self, conn: Connection, args: dict[str, Any]) -> dict[str, Any]:
        return {"state": self.state(), "tracker": self.tracker.to_dict()}

    def _cmd_control(self, conn: Connection, args: dict[str, Any]) -> dict[str, Any]:
        with self._clients_lock:
            old = self.controller
            if old is not None and old is not conn:
                if not args.get("take"):
                    raise ServerError(f"{old.describe()} controls the rig; send control with "
                                      "take=true to take it over.")
                old.send({"type": "control", "controller": conn.public(),
                          "text": f"{conn.describe()} took control"})
                self.log(f"{conn.describe()} took control from {old.describe()}", "warning")
            self.controller = conn
        return {"controller": conn.public()}

    def _cmd_release(self, conn: Connection, args: dict[str, Any]) -> None:
        with self._clients_lock:
            if self.controller is conn:
                self.controller = None

    def _cmd_shutdown(self, conn: Connection, rid: Any, args: dict[str, Any]) -> None:
        """Answer first, then stop (the stop closes this connection too)."""
        abort = bool(args.get("abort"))
        self._refuse_stop_during_scan(abort)
        conn.send({"type": "reply", "id": rid, "ok": True, "result": {"stopping": True}})
        self.shutdown(f"dotshell stop from {conn.describe()}", abort=abort)

    def _cmd_bye(self, conn: Connection, args: dict[str, Any]) -> None:
        conn.close("said bye")

    def _cmd_restart_worker(self, conn: Connection, args: dict[str, Any]) -> dict[str, Any]:
        """End the session worker (a scan aborted, its run marked) and start a new one."""
        if self.worker is None:
            raise ServerError("this server holds its session in its own process (no worker to "
                              "restart); stop it with dotshell stop --abort and start it again.")
        self.log(f"{conn.describe()} restarts the session worker (pid {self.worker.pid})",
                 "warning")
        return {"pid": self.worker.restart(f"restart requested by {conn.describe()}")}

    # ---- state, events, polling ---------------------------------------------------------------------

    def state(self) -> dict[str, Any]:
        """What every client shows about the session (docs/server.md)."""
        s = self.session
        with self._clients_lock:
            clients = [c.public() for c in self.clients if c.greeted]
            controller = self.controller.public() if self.controller else None
        run = s.run
        return {"server": {"name": self.name, "pid": os.getpid(), "socket": str(self.socket_path),
                           "log": str(self.log_path), "started": self.started,
                           "version": __version__, "protocol": PROTOCOL_VERSION,
                           "on_hangup": self.on_hangup, "exit_when_idle": self.exit_when_idle,
                           "stopping": self._stopping.is_set()},
                "profile": s.summary if isinstance(s, WorkerSession) else profile_summary(s),
                "out_dir": str(s.out_dir.resolve()),
                "session": s.state, "connected": s.connected, "projected": s.projected,
                "run": {"dir": str(run.root), "status": run.status} if run else None,
                "controller": controller, "clients": clients,
                "console": {"busy": self.console.busy, "prompt": self.console.waiting_prompt},
                "worker": self.worker.describe() if self.worker else None}

    def push_state(self) -> None:
        """Send the state to every client if it changed since the last time."""
        try:
            state = self.state()
        except Exception as exc:  # a half-loaded profile: try again at the next poll
            self.log(f"state unavailable: {type(exc).__name__}: {exc}", "debug")
            return
        with self._event_lock:  # not between a hello's reply and its client's greeting
            if state != self._last_state:
                self._last_state = state
                self.broadcast({"type": "state", "state": state})

    def _on_event(self, ev: Event) -> None:
        wire = ev.to_dict()
        level, text = describe_event(ev)
        if isinstance(ev, ScanStarted):
            self._open_run_log(Path(ev.run_dir))
        self.log(text, level, ev.time)
        if isinstance(ev, ScanFinished):
            self._close_run_log()
        with self._event_lock:
            self.tracker.update(ev)
            self.backlog.append(wire)
            self.broadcast({"type": "event", "event": wire})
        if isinstance(ev, LIFECYCLE):
            self.push_state()
        if isinstance(ev, ScanFinished) and self.session.job is not None:
            job = self.session.job  # the session turns idle once scan() has returned
            def after_scan() -> None:
                job.thread.join()
                self.push_state()

            threading.Thread(target=after_scan, daemon=True).start()

    def _on_worker_change(self) -> None:
        """The worker's mirror (or its health) changed: clients see it at once."""
        with self._clients_lock:
            watched = bool(self.clients)
        if watched:
            self._push_devices()
            self.push_state()

    def _poll(self) -> None:
        while not self._stopping.wait(self.poll_s):
            with self._clients_lock:
                watched = bool(self.clients)
            if watched:
                self._push_devices()
                self.push_state()
            elif (self.exit_when_idle and not self.session.scanning
                  and time.monotonic() - self._last_activity > IDLE_GRACE_S):
                self.log("no client attached and no scan running: exiting (exit_when_idle)")
                self.shutdown("idle", abort=False)

    def _push_devices(self) -> None:
        try:
            rows = self.session.devices()
        except Exception as exc:  # a misbehaving backend must not stop the server
            rows = [{"role": "?", "backend": "?", "connected": False,
                     "status": {"error": f"{type(exc).__name__}: {exc}"}}]
        rows = decode(encode({"rows": rows}))["rows"]  # as the clients will see them
        with self._event_lock:  # else a client greeted meanwhile could miss these rows or get
            if rows != self._last_rows:  # them before its hello reply, whose older ones won
                self._last_rows = rows
                self.broadcast({"type": "devices", "rows": rows})

    # ---- logs ------------------------------------------------------------------------------------------

    def log(self, text: str, level: str = "info", when: float | None = None) -> None:
        """One line in the server log (and the running scan's); echoed to stderr if asked."""
        stamp = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(when or time.time()))
        line = f"{stamp} {level:<7} {text}\n"
        with self._log_lock:
            for f in (self._log, self._run_log):
                if f is not None and not f.closed:
                    f.write(line)
            if self.echo:
                sys.stderr.write(line)

    def _open_run_log(self, run_dir: Path) -> None:
        with self._log_lock:
            self._close_run_log()
            try:
                self._run_log = open(run_dir / "server.log", "a", encoding="utf-8", buffering=1)  # noqa: SIM115
            except OSError as exc:
                self._run_log = None
                self.log(f"cannot write {run_dir / 'server.log'}: {exc}", "warning")

    def _close_run_log(self) -> None:
        with self._log_lock:
            if self._run_log is not None:
                self._run_log.close()
                self._run_log = None
