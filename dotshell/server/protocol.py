"""The wire format between the rig server and its front ends (docs/server.md).

One JSON object per line (UTF-8, ``\\n``-terminated) in both directions over a Unix-domain
stream socket. A client sends requests ``{"id": N, "cmd": NAME, ...arguments}``; the server
answers each with ``{"type": "reply", "id": N, "ok": true, "result": ...}`` or ``{"type":
"reply", "id": N, "ok": false, "error": TEXT, "kind": ERROR CLASS}``, and pushes ``event``,
``state``, ``devices``, ``console``, ``console_input``, ``console_done``, ``control`` and
``bye`` messages whenever they happen.
"""

from __future__ import annotations

import dataclasses
import json
import socket
import threading
from pathlib import Path
from typing import Any, Iterator

from dotshell.errors import DotshellError
from dotshell.events import Event

#: Bumped on any incompatible change; the server refuses a client that speaks another one.
#: 2: ``halt`` (the stop key) and ``configure``; ``abort`` and ``stop`` need control.
PROTOCOL_VERSION = 2
#: Longest line either side accepts (bytes): a console input, a status reply.
MAX_LINE = 4 * 1024 * 1024

#: Requests any attached client may send (``halt``, the stop key, stops motion and never
#: aborts: whoever sees the rig may stop it; aborting a scan is the controller's).
OPEN_COMMANDS = frozenset({"hello", "state", "devices", "patterns", "plugins", "history",
                           "control", "release", "halt", "shutdown", "bye",
                           "restart_worker"})
#: Requests that change the rig or the session: only the client in control may send them.
CONTROL_COMMANDS = frozenset({"load", "set", "configure", "connect", "disconnect", "move",
                              "jog", "home", "analyzer", "exposure", "project", "snap",
                              "decode", "scan", "pause", "resume", "abort", "stop", "normalize",
                              "console", "console_reply", "console_interrupt", "complete"})
#: Requests answered at once by the connection's reader, never queued behind a slow one.
URGENT_COMMANDS = frozenset({"hello", "state", "control", "release", "abort", "stop", "halt", "pause",
                             "resume", "console_reply", "console_interrupt", "shutdown", "bye",
                             "restart_worker"})


class ServerError(DotshellError):
    """No server answers, the server refused a request, or it went away."""


class RemoteError(DotshellError):
    """A request failed in the server; ``kind`` is the exception class it raised there."""

    def __init__(self, message: str, kind: str = "DotshellError") -> None:
        super().__init__(message)
        self.kind = kind


def _plain(o: Any) -> Any:
    """JSON fallback for numpy scalars and arrays, paths, sets and dataclasses."""
    if hasattr(o, "item") and callable(o.item) and getattr(o, "ndim", 1) == 0:
        return o.item()
    if hasattr(o, "tolist"):
        return o.tolist()
    if isinstance(o, (Path, set, frozenset)):
        return str(o) if isinstance(o, Path) else sorted(o)
    if dataclasses.is_dataclass(o) and not isinstance(o, type):
        return dataclasses.asdict(o)
    return repr(o)


def encode(message: dict[str, Any]) -> bytes:
    """One message as a line of compact JSON."""
    return json.dumps(message, default=_plain, separators=(",", ":")).encode() + b"\n"


def decode(line: bytes) -> dict[str, Any]:
    """One received line as a message; ServerError when it is not a JSON object."""
    try:
        message = json.loads(line)
    except ValueError as exc:
        raise ServerError(f"not a protocol line ({exc}): {line[:80]!r}") from None
    except RecursionError:  # JSON nested deeper than Python's stack: refused, never fatal
        raise ServerError(f"not a protocol line (nested too deeply): {line[:80]!r}") from None
    if not isinstance(message, dict):
        raise ServerError(f"not a protocol message (a JSON object): {line[:80]!r}")
    return message


def read_lines(sock: socket.socket, stop: threading.Event | None = None) -> Iterator[bytes]:
    """The non-empty lines a peer sends (without the newline) until it closes the connection
    or ``stop`` is set; ServerError when a line grows past :data:`MAX_LINE`."""
    buf = b""
    while stop is None or not stop.is_set():
        data = sock.recv(65536)
        if not data:
            return
        buf += data
        while b"\n" in buf:
            line, buf = buf.split(b"\n", 1)
            if line.strip():
                yield line
        if len(buf) > MAX_LINE:
            raise ServerError(f"a line longer than {MAX_LINE} bytes; the connection is closed.")


def peer_uid(sock: socket.socket) -> int:
    """The user id of the process at the other end of a Unix socket (Linux SO_PEERCRED)."""
    import struct

    _, uid, _ = struct.unpack("3i", sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED,
                                                    struct.calcsize("3i")))
    return uid


def error_reply(request_id: Any, exc: BaseException) -> dict[str, Any]:
    text = str(exc) if isinstance(exc, DotshellError) else f"{type(exc).__name__}: {exc}"
    return {"type": "reply", "id": request_id, "ok": False, "error": text,
            "kind": type(exc).__name__}


def raise_remote(reply: dict[str, Any]) -> None:
    """Re-raise a failed reply in the client: as the same :class:`DotshellError` class when
    this side knows it (so ``except DeviceError`` works on both sides), else as
    :class:`RemoteError`."""
    kind, text = reply.get("kind", "DotshellError"), reply.get("error", "the request failed")
    cls = _subclasses(DotshellError).get(kind)
    if cls is not None and cls is not RemoteError:
        raise cls(text)
    raise RemoteError(text, kind)


def _subclasses(base: type) -> dict[str, type]:
    """Every class below ``base`` imported so far, by name (the first one of a name wins)."""
    found: dict[str, type] = {base.__name__: base}
    todo: list[type] = [base]
    sub: type
    while todo:
        for sub in todo.pop().__subclasses__():
            found.setdefault(sub.__name__, sub)
            todo.append(sub)
    return found


# ---- events ---------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class UnknownEvent(Event):
    """An event class this client does not know (a newer server, a plugin's own event)."""

    name: str
    fields: dict[str, Any] = dataclasses.field(default_factory=dict)


def event_from_wire(data: dict[str, Any]) -> Event:
    """The event a server sent (``Event.to_dict()`` form) as an instance of its class."""
    data = dict(data)
    name = data.pop("event", "?")
    cls = _subclasses(Event).get(name)
    if cls is not None and cls is not UnknownEvent:
        names = {f.name for f in dataclasses.fields(cls)}
        try:
            return cls(**{k: v for k, v in data.items() if k in names})
        except TypeError:
            pass  # fields changed between versions: keep it readable instead
    stamp = data.pop("time", None)
    return UnknownEvent(name=name, fields=data, **({"time": stamp} if stamp else {}))
