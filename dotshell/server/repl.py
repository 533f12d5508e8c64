"""The Python console inside the rig server: one :class:`Interpreter` on the session's
namespace, shared by every front end. Input comes from the client in control; output, results,
tracebacks and ``input()`` prompts go to every client as ``console`` / ``console_input`` /
``console_done`` messages (batched, so a printing loop cannot flood a slow terminal); the
history is kept in the user's state directory across servers and restarts."""

from __future__ import annotations

import json
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any, Callable

from dotshell.session.console import Session, SessionBusy, readable_repr
from dotshell.events import Event
from dotshell.server.describe import describe_event
from dotshell.server.interpreter import Interpreter
from dotshell.runtime.paths import open_private

#: Inputs kept in the history file and offered to ↑/↓.
HISTORY_SIZE = 1000
#: Output is sent at most this often (seconds) and in pieces of at most this many characters.
FLUSH_S = 0.05
FLUSH_CHARS = 64 * 1024
#: The console's last messages a newly attached front end is shown (at most this many
#: characters of text: older ones are dropped first).
TRANSCRIPT_CHARS = 200_000


def read_history(path: Path | None) -> list[str]:
    """The last :data:`HISTORY_SIZE` inputs of a history file (JSON lines); [] when absent or
    unreadable lines are skipped."""
    if path is None or not path.is_file():
        return []
    out = []
    for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
        try:
            entry = json.loads(line)
        except ValueError:
            continue
        if isinstance(entry, dict) and isinstance(entry.get("source"), str):
            out.append(entry["source"])
    return out[-HISTORY_SIZE:]


class Transcript:
    """A console's last messages as they were pushed, oldest first: at most
    :data:`TRANSCRIPT_CHARS` characters of text (the oldest dropped first; a long oldest output
    keeps its end). Shown to a front end that attaches later."""

    def __init__(self, limit: int | None = None) -> None:
        self._limit = limit  # None: TRANSCRIPT_CHARS as it is when a message is added
        self.lock = threading.RLock()
        self._messages: deque[dict[str, Any]] = deque()
        self._chars = 0

    def add(self, message: dict[str, Any]) -> None:
        with self.lock:
            self._messages.append(message)
            self._chars += len(message.get("text") or "")
            limit = TRANSCRIPT_CHARS if self._limit is None else self._limit
            while self._chars > limit:
                oldest = self._messages[0]
                text, excess = oldest.get("text") or "", self._chars - limit
                if len(text) > excess:  # keep the end of a long output
                    self._messages[0] = {**oldest, "text": text[excess:]}
                    self._chars -= excess
                else:
                    self._messages.popleft()
                    self._chars -= len(text)

    def messages(self) -> list[dict[str, Any]]:
        with self.lock:
            return list(self._messages)


class ServerConsole:
    """The console service. ``send(message)`` delivers a message to every client."""

    def __init__(self, session: Session, send: Callable[[dict[str, Any]], None],
                 history_file: Path | None = None) -> None:
        self.session = session
        self._broadcast = send
        self.kept = Transcript()
        #: held while a message is kept and sent: a front end greeted under it gets each
        #: console message once, in the transcript or pushed after it
        self.lock = self.kept.lock
        self.history_file = history_file
        self.history = read_history(history_file)
        self.interpreter = Interpreter(session.namespace(), self._write,
                                       on_interrupt=self._abort_scan, on_input=self._ask,
                                       display=readable_repr)
        session.bus.subscribe(self._on_event)
        self._pending: list[tuple[str, str]] = []
        self._pending_lock = threading.Lock()
        self._timer: threading.Timer | None = None
        self._thread: threading.Thread | None = None

    def send(self, message: dict[str, Any]) -> None:
        """Keep ``message`` in the bounded transcript and send it to every front end."""
        with self.lock:
            self.kept.add(message)
            self._broadcast(message)

    def transcript(self) -> list[dict[str, Any]]:
        """The console's last messages (:class:`Transcript`); call it holding :attr:`lock` to
        add nothing meanwhile."""
        return self.kept.messages()

    @property
    def busy(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    @property
    def waiting_prompt(self) -> str | None:
        return self.interpreter.waiting_prompt

    def run(self, source: str) -> int:
        """Start running ``source`` on the console thread; returns its input number."""
        if self.busy:
            raise SessionBusy("the console is still running the previous input; interrupt it "
                              "first (ctrl+c in the TUI).")
        self._remember(source)
        self.send({"type": "console", "kind": "input", "text": source})
        self._thread = threading.Thread(target=self._run, args=(source,), daemon=True,
                                        name="dotshell-console")
        self._thread.start()
        return self.interpreter.count + 1

    def _run(self, source: str) -> None:
        ok = self.interpreter.run(source)
        self._flush()
        self._thread = None  # idle before console_done: a client may send its next input at once
        self.send({"type": "console_done", "ok": ok})

    def _remember(self, source: str) -> None:
        if not self.history or self.history[-1] != source:
            self.history.append(source)
            del self.history[:-HISTORY_SIZE]
            if self.history_file is not None:
                with open_private(self.history_file) as f:
                    f.write(json.dumps({"time": time.time(), "source": source}) + "\n")

    def _on_event(self, ev: Event) -> None:
        """A line for the session's events while an input runs, from the session's
        :meth:`~dotshell.session.console.Session.log_level` on (progress by default, not a line per
        frame)."""
        if not self.interpreter.busy:
            return
        level, text = describe_event(ev)
        if self.session.shows(level):
            self._write("log", f"{level}: {text}\n" if level != "info" else f"{text}\n")

    # ---- output, batched ----------------------------------------------------------------------

    def _write(self, kind: str, text: str) -> None:
        with self._pending_lock:
            if self._pending and self._pending[-1][0] == kind:
                self._pending[-1] = (kind, self._pending[-1][1] + text)
            else:
                self._pending.append((kind, text))
            big = sum(len(t) for _, t in self._pending) >= FLUSH_CHARS
            if not big and self._timer is None:
                self._timer = threading.Timer(FLUSH_S, self._flush)
                self._timer.daemon = True
                self._timer.start()
        if big or kind in ("result", "error"):
            self._flush()

    def _flush(self) -> None:
        with self._pending_lock:
            pending, self._pending = self._pending, []
            if self._timer is not None:
                self._timer.cancel()
                self._timer = None
        for kind, text in pending:
            self.send({"type": "console", "kind": kind, "text": text})

    # ---- input(), interrupts, completion -------------------------------------------------------

    def _ask(self, prompt: str) -> None:
        self._flush()
        self.send({"type": "console_input", "prompt": prompt})

    def reply(self, line: str | None) -> bool:
        return self.interpreter.reply(line)

    def interrupt(self) -> bool:
        return self.interpreter.interrupt()

    def _abort_scan(self) -> bool:
        if self.session.state in ("running", "paused"):
            self.session.abort()
            return True
        return False

    def complete(self, text: str) -> dict[str, Any]:
        token, matches = self.interpreter.complete(text)
        return {"token": token, "matches": matches}
