"""The session worker: the process that holds the rig server's session — the profile, the rig
and its drivers, the scan, the Python console — so that a driver hung in C (a camera SDK that
blocks holding the GIL) stops only this process, never the server and its clients.

The rig server starts it (:class:`dotshell.server.supervisor.WorkerSession`) as
``python -m dotshell.server.worker SPEC`` with one end of a socket pair and the call board
(:mod:`dotshell.server.callboard`) as inherited file descriptors, and talks to it in JSON lines
(:mod:`dotshell.server.protocol`'s encoding):

* server → worker: ``{"id": N, "cmd": NAME, "args": {...}}``: the session requests of
  :data:`dotshell.server.commands.COMMANDS`, plus ``ping`` and ``close``.
* worker → server: ``reply`` (as to a client), ``event`` (every event of the session's bus),
  ``push`` (a console message for every client), ``mirror`` (what the server shows of the
  session: state, devices, run, profile, console; sent when it changes) and, once, ``ready``.

``ping``, ``abort``, ``stop``, ``pause``, ``resume``, ``console_reply`` and
``console_interrupt`` are answered by the reading thread at once; every other request runs on a
thread of its own, as each client's requests did in the server.
"""

from __future__ import annotations

import json
import os
import socket
import sys
import threading
import time
from pathlib import Path
from typing import Any

from dotshell.events import Event, ScanFinished, ScanPaused, ScanResumed, ScanStarted
from dotshell.server.protocol import decode, encode, error_reply, read_lines

#: How often the worker looks for a change of what the server mirrors (seconds).
MIRROR_S = 0.25
#: Answered by the reading thread, never behind a running request.
INLINE = frozenset({"ping", "abort", "stop", "halt", "pause", "resume", "console_reply",
                    "console_interrupt"})
LIFECYCLE = (ScanStarted, ScanFinished, ScanPaused, ScanResumed)


class SessionWorker:
    """Serves one session to the rig server over ``sock``."""

    def __init__(self, sock: socket.socket, session: Any, history_file: Path | None) -> None:
        from dotshell.server.commands import Context
        from dotshell.server.repl import ServerConsole

        self.sock = sock
        self.session = session
        self._send_lock = threading.Lock()
        self.console = ServerConsole(session, lambda m: self.send({"type": "push", "message": m}),
                                     history_file)
        self.context = Context(session, self.console)
        self._last_mirror: dict[str, Any] | None = None
        self._mirror_lock = threading.Lock()
        self._closing = threading.Event()
        session.bus.subscribe(self._on_event)

    def send(self, message: dict[str, Any]) -> None:
        data = encode(message)
        with self._send_lock:
            try:
                self.sock.sendall(data)
            except OSError:  # the server is gone: nothing to tell
                self._closing.set()

    # ---- what the server mirrors ----------------------------------------------------------------

    def mirror(self) -> dict[str, Any]:
        from dotshell.server.commands import profile_summary

        s, c = self.session, self.console
        run = s.run
        try:
            rows = s.devices()
        except Exception as exc:  # a misbehaving backend must not stop the worker
            rows = [{"role": "?", "backend": "?", "connected": False,
                     "status": {"error": f"{type(exc).__name__}: {exc}"}}]
        return {"state": s.state, "connected": s.connected, "projected": s.projected,
                "run": {"dir": str(run.root), "status": run.status} if run else None,
                "out_dir": str(s.out_dir.resolve()), "profile": profile_summary(s),
                "profile_path": str(s.profile_path.resolve()) if s.profile_path else None,
                "rows": rows, "console": {"busy": c.busy, "prompt": c.waiting_prompt},
                "history": c.history[-500:]}

    def push_mirror(self) -> None:
        """Send the mirror if it changed (rows as the clients will see them)."""
        with self._mirror_lock:
            try:
                m = json.loads(encode(self.mirror()))
            except Exception as exc:  # a half-loaded profile: try again shortly
                print(f"mirror unavailable: {type(exc).__name__}: {exc}", file=sys.stderr)
                return
            if m != self._last_mirror:
                self._last_mirror = m
                self.send({"type": "mirror", "mirror": m})

    def _mirror_loop(self) -> None:
        while not self._closing.wait(MIRROR_S):
            self.push_mirror()

    def _on_event(self, ev: Event) -> None:
        if isinstance(ev, LIFECYCLE):
            self.push_mirror()  # the server's state is current when its clients get the event
        self.send({"type": "event", "event": ev.to_dict()})
        job = self.session.job
        if isinstance(ev, ScanFinished) and job is not None:  # idle (and its run set) once
            def after_scan() -> None:  # scan() has returned
                job.thread.join()
                self.push_mirror()

            threading.Thread(target=after_scan, daemon=True, name="dotshell-scan-end").start()

    # ---- requests -------------------------------------------------------------------------------

    def serve(self) -> None:
        threading.Thread(target=self._mirror_loop, daemon=True, name="dotshell-mirror").start()
        self.push_mirror()
        self.send({"type": "ready", "pid": os.getpid()})
        try:
            for line in read_lines(self.sock):
                message = decode(line)
                cmd = message.get("cmd")
                if cmd == "close":
                    self._close(message.get("id"))
                    return
                if cmd in INLINE:
                    self._handle(message)
                else:
                    threading.Thread(target=self._handle, args=(message,), daemon=True,
                                     name=f"dotshell-request-{cmd}").start()
        except OSError:
            pass
        self._close(None)  # the server went away: leave the rig safe

    def _handle(self, message: dict[str, Any]) -> None:
        from dotshell.server.commands import COMMANDS

        rid, cmd = message.get("id"), message.get("cmd")
        try:
            if cmd == "ping":
                result: Any = {"pong": time.time()}
            else:
                result = COMMANDS[str(cmd)](self.context, dict(message.get("args") or {}))
            reply = {"type": "reply", "id": rid, "ok": True, "result": result}
        except Exception as exc:  # the request failed; the worker lives on
            reply = error_reply(rid, exc)
        if cmd != "ping":
            self.push_mirror()  # before the reply: a client acting on it sees the new state
        self.send(reply)

    def _close(self, rid: Any) -> None:
        """Abort a scan (frames kept), stop the devices, close the rig, then answer."""
        try:
            self.session.stop()
            self.console.interrupt()
            while self.session.scanning:
                time.sleep(0.05)
            self.session.close()
            reply = {"type": "reply", "id": rid, "ok": True, "result": None}
        except Exception as exc:  # closing must go on whatever a device does
            reply = error_reply(rid, exc)
        self._closing.set()
        if rid is not None:
            self.push_mirror()
            self.send(reply)


def main(argv: list[str] | None = None) -> int:
    """``python -m dotshell.server.worker SPEC``: SPEC is JSON with ``sock_fd``, ``board_fd``,
    ``profile``, ``out``, ``overrides``, ``strict_plugins`` and ``history``."""
    spec = json.loads((argv or sys.argv)[1])
    sock = socket.socket(fileno=spec["sock_fd"])
    from dotshell.rig import handles
    from dotshell.server.callboard import CallBoard

    handles.call_watcher = CallBoard(spec["board_fd"])
    try:
        session = _open_session(spec)
    except Exception as exc:  # the server says it and exits like a server that failed to load
        sock.sendall(encode(error_reply("ready", exc)))
        return 2
    worker = SessionWorker(sock, session, Path(spec["history"]) if spec.get("history") else None)
    worker.serve()
    return 0


def _open_session(spec: dict[str, Any]) -> Any:
    from dotshell.session.console import Session
    from dotshell.plugins import get_plugin_manager
    from dotshell.runtime.process import configure_process

    configure_process()
    pm = get_plugin_manager(strict=bool(spec.get("strict_plugins")))
    session = Session(spec.get("profile"), pm=pm, out_dir=spec["out"],
                      overrides=spec.get("overrides") or ())
    for e in pm.load_errors:
        session.bus.warn(f"plugin failed to load: {e}")
    return session


if __name__ == "__main__":
    sys.exit(main())
