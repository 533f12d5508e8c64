"""The front ends' side of the rig server: :class:`ServerClient` (requests and pushed messages
over the socket) and :class:`RemoteSession` (the same actions as
:class:`~dotshell.session.console.Session`, each a request, with the server's state mirrored).

Cheap to import (no numpy, no plugins): a front end holds no frames and no devices.
"""

from __future__ import annotations

import itertools
import os
import socket
import threading
from pathlib import Path
from typing import Any, Callable

from dotshell.events import Event
from dotshell.server.progress import ScanTracker
from dotshell.server.protocol import (PROTOCOL_VERSION, ServerError, decode, encode,
                                      event_from_wire, peer_uid, raise_remote, read_lines)

Handler = Callable[[dict[str, Any]], None]


def tty_name() -> str | None:
    """The terminal of this process (``/dev/pts/3``), or None."""
    for fd in (0, 1, 2):
        try:
            return os.ttyname(fd)
        except OSError:
            continue
    return None


class _Pending:
    def __init__(self, on_result: Callable[[Any], None] | None = None) -> None:
        self.done = threading.Event()
        self.reply: dict[str, Any] | None = None
        self.on_result = on_result


class ServerClient:
    """A connection to the server on ``path``. Messages the server pushes go to the
    subscribers (``subscribe``); those that arrive before the first subscriber are kept for
    it. A lost connection is announced to them as ``{"type": "closed", "reason": ...}``."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            self.sock.connect(os.fspath(self.path))
        except OSError as exc:
            self.sock.close()
            raise ServerError(f"no rig server answers on {self.path} ({exc.strerror or exc}); "
                              "start one with dotshell serve PROFILE (dotshell tui PROFILE "
                              "starts one itself).") from None
        uid = peer_uid(self.sock)
        if uid != os.getuid():  # a socket another user planted: never send it a request
            self.sock.close()
            raise ServerError(f"the server on {self.path} runs as another user (uid {uid}, "
                              f"you are {os.getuid()}); dotshell talks only to your own "
                              "servers. Give the socket of a server you started, or leave "
                              "out --socket.")
        self._ids = itertools.count(1)
        self._pending: dict[int, _Pending] = {}
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        self._handlers: list[Handler] = []
        self._early: list[dict[str, Any]] | None = []
        self.closed = threading.Event()
        self.close_reason = ""
        self._reader = threading.Thread(target=self._read, daemon=True, name="dotshell-client")
        self._reader.start()

    # ---- requests -------------------------------------------------------------------------------

    def call(self, cmd: str, timeout: float | None = None,
             on_result: Callable[[Any], None] | None = None, **args: Any) -> Any:
        """Send a request and wait for its reply; the result, or the server's error raised
        (as the same :mod:`dotshell.errors` class). ``on_result(result)`` runs on the reader
        thread as the reply arrives, before any message the server sent after it."""
        rid = next(self._ids)
        pending = _Pending(on_result)
        with self._lock:
            if self.closed.is_set():
                raise ServerError(f"the rig server is gone ({self.close_reason}).")
            self._pending[rid] = pending
        self._send({"id": rid, "cmd": cmd, **args})
        if not pending.done.wait(timeout):
            with self._lock:
                self._pending.pop(rid, None)
            raise ServerError(f"the rig server did not answer {cmd} within {timeout} s.")
        reply = pending.reply
        if reply is None:
            raise ServerError(f"the rig server went away during {cmd} ({self.close_reason}).")
        if not reply.get("ok"):
            raise_remote(reply)
        return reply.get("result")

    def _send(self, message: dict[str, Any]) -> None:
        try:
            with self._send_lock:
                self.sock.sendall(encode(message))
        except OSError as exc:
            raise ServerError(f"cannot reach the rig server on {self.path}: {exc}") from None

    # ---- pushed messages ---------------------------------------------------------------------------

    def subscribe(self, fn: Handler) -> Callable[[], None]:
        """Call ``fn(message)`` for every pushed message (on the reader thread)."""
        with self._lock:
            early, self._early = self._early or [], None
            self._handlers.append(fn)
            for message in early:
                fn(message)
        return lambda: self._handlers.remove(fn) if fn in self._handlers else None

    def on_message(self, message: dict[str, Any]) -> None:
        """Seen first, before the subscribers (subclasses mirror state here)."""

    def _read(self) -> None:
        try:
            for line in read_lines(self.sock):
                self._deliver(decode(line))
        except (OSError, ServerError):
            pass
        self._lost(self.close_reason or "the connection closed")

    def _deliver(self, message: dict[str, Any]) -> None:
        if message.get("type") == "reply":
            with self._lock:
                pending = self._pending.pop(message.get("id"), None)  # type: ignore[arg-type]
            if pending is not None:
                pending.reply = message
                try:
                    if message.get("ok") and pending.on_result is not None:
                        pending.on_result(message.get("result"))
                finally:
                    pending.done.set()
            return
        if message.get("type") == "bye":
            self.close_reason = f"the server stopped: {message.get('reason', '')}"
        self.on_message(message)
        with self._lock:
            if self._early is not None:
                self._early.append(message)
                return
            handlers = list(self._handlers)
        for fn in handlers:
            fn(message)

    def _lost(self, reason: str) -> None:
        with self._lock:
            if self.closed.is_set():
                return
            self.close_reason = reason
            self.closed.set()
            pending, self._pending = list(self._pending.values()), {}
        for p in pending:
            p.done.set()
        self._deliver({"type": "closed", "reason": reason})

    def close(self) -> None:
        """Detach: say bye and close the socket (the server and its scan go on)."""
        if not self.closed.is_set():
            try:
                self._send({"cmd": "bye"})
            except ServerError:
                pass
        self.close_reason = self.close_reason or "detached"
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self._reader.join(5)
        self.sock.close()


class RemoteSession(ServerClient):
    """A session in a rig server, seen from a front end.

    Args:
        path: the server's socket.
        client: how this front end is named in the server's log and ``dotshell status``.
        control: ask for control at once (granted when nobody has it).

    After the ``hello``: :attr:`state` (the server's state, kept current), :attr:`rows` (device
    status rows), :attr:`tracker` (the scan's progress so far), :attr:`backlog` (recent events)
    and :attr:`history` (console inputs). Paths are sent absolute.
    """

    def __init__(self, path: Path | str, client: str = "cli", control: bool = False) -> None:
        super().__init__(path)
        self.state: dict[str, Any] = {}
        self.rows: list[dict[str, Any]] = []
        welcome = self.call("hello", protocol=PROTOCOL_VERSION, client=client, pid=os.getpid(),
                            tty=tty_name(), control=control, timeout=60, on_result=self._greeted)
        self.id: int = welcome["you"]
        self.tracker = ScanTracker.from_dict(welcome["tracker"])
        self.backlog: list[Event] = [event_from_wire(e) for e in welcome["backlog"]]
        self.history: list[str] = list(welcome["history"])
        #: the console's last messages before this client attached (bounded), oldest first
        self.console_transcript: list[dict[str, Any]] = list(welcome.get("console") or [])

    def _greeted(self, welcome: dict[str, Any]) -> None:
        """The hello's state and device rows, taken on the reader thread: a state or rows
        pushed right after the reply are newer, and are applied after these (taken on the
        calling thread, the reply's could land after them and hide them)."""
        self.state = welcome["state"]
        self.rows = welcome.get("rows") or []

    def on_message(self, message: dict[str, Any]) -> None:
        kind = message.get("type")
        if kind == "state":
            self.state = message["state"]
        elif kind == "devices":
            self.rows = message["rows"]

    # ---- what the server says ----------------------------------------------------------------------

    @property
    def profile(self) -> dict[str, Any] | None:
        """The loaded profile's summary (name, source, path, views, exposure_ms, coding,
        roles), or None."""
        return self.state.get("profile")

    @property
    def session_state(self) -> str:
        """``idle``, ``running``, ``paused`` or ``stopping``."""
        return self.state.get("session", "idle")

    @property
    def scanning(self) -> bool:
        return self.session_state != "idle"

    @property
    def projected(self) -> str | None:
        return self.state.get("projected")

    @property
    def controller(self) -> dict[str, Any] | None:
        return self.state.get("controller")

    @property
    def in_control(self) -> bool:
        c = self.controller
        return c is not None and c.get("id") == self.id

    @property
    def server_name(self) -> str:
        return self.state.get("server", {}).get("name", "?")

    # ---- actions (each one request; errors raised as in Session) -------------------------------------

    def load(self, path: str | Path, overrides: list[str] | tuple[str, ...] = ()) -> Any:
        return self.call("load", path=str(Path(path).expanduser().resolve()),
                         overrides=list(overrides))

    def set(self, *overrides: str) -> Any:
        return self.call("set", overrides=list(overrides))

    def configure(self, **settings: Any) -> Any:
        """The next scan's settings: ``views``, ``exposure_ms``, ``pdi_angles_deg``,
        ``out_dir`` (see :meth:`dotshell.session.console.Session.configure`)."""
        if settings.get("out_dir") is not None:
            settings["out_dir"] = str(Path(settings["out_dir"]).expanduser().resolve())
        return self.call("configure", **settings)

    def connect(self) -> Any:
        return self.call("connect")

    def disconnect(self) -> Any:
        return self.call("disconnect")

    def move_to(self, degrees: float) -> float:
        return self.call("move", degrees=float(degrees))

    def jog(self, degrees: float) -> float:
        return self.call("jog", degrees=float(degrees))

    def home(self, role: str = "stage") -> float | None:
        return self.call("home", role=role)

    def set_analyzer(self, degrees: float) -> float:
        return self.call("analyzer", degrees=float(degrees))

    def set_exposure(self, ms: float) -> float:
        return self.call("exposure", ms=float(ms))

    def patterns(self) -> list[str]:
        return self.call("patterns")

    def project(self, name: str) -> str:
        return self.call("project", name=name)

    def snap(self) -> dict[str, Any]:
        return self.call("snap")

    def decode(self) -> dict[str, Any]:
        return self.call("decode")

    def scan(self, out: str | Path | None = None,
             calibration: str | Path | None = None) -> dict[str, Any]:
        """Start a scan on the server; returns ``{"run_dir": ...}`` once it runs."""
        return self.call("scan", out=str(Path(out).resolve()) if out is not None else None,
                         calibration=str(Path(calibration).resolve()) if calibration else None)

    def pause(self) -> None:
        self.call("pause")

    def resume(self) -> None:
        self.call("resume")

    def abort(self) -> None:
        self.call("abort")

    def stop(self) -> None:
        self.call("stop")

    def halt(self) -> str:
        """The stop key: pause a running scan before its next frame, else stop every device
        that can move; never aborts (open to watchers too)."""
        return self.call("halt")

    def devices(self) -> list[dict[str, Any]]:
        return self.call("devices")

    def plugins(self) -> dict[str, Any]:
        return self.call("plugins")

    def console_run(self, source: str) -> Any:
        return self.call("console", source=source)

    def console_reply(self, text: str | None) -> Any:
        return self.call("console_reply", text=text)

    def console_interrupt(self) -> Any:
        return self.call("console_interrupt")

    def complete(self, text: str) -> dict[str, Any]:
        return self.call("complete", text=text)

    def take_control(self) -> Any:
        return self.call("control", take=True)

    def shutdown(self, abort: bool = False) -> Any:
        return self.call("shutdown", abort=abort)

    def refresh(self) -> dict[str, Any]:
        """Ask for the state now (it is also pushed whenever it changes)."""
        reply = self.call("state")
        self.state = reply["state"]
        return reply
