"""The Console panel: a Python console bound to the live session (``rig``, ``profile``,
``run``, ``scan()``, ``np`` and the rest of :meth:`dotshell.console.Session.namespace`).
Input runs in a worker thread; output, results and tracebacks appear in the pane as they come."""

from __future__ import annotations

from typing import Any

from rich.text import Text
from textual.app import ComposeResult
from textual.containers import Vertical
from textual.message import Message
from textual.widgets import RichLog, Static

from dotshell.console import Session
from dotshell.tui.interpreter import Interpreter
from dotshell.tui.widgets.console_input import ConsoleInput

BANNER = ("Python console on the live session: rig, profile, run, session, np, dotshell; "
          "connect(), jog(deg), move_to(deg), snap(), project(name), patterns(), decode(), "
          "scan(), pause(), resume(), abort(). Enter runs, a blank line ends a block, ↑/↓ "
          "history, ctrl+c interrupts.")
STYLES = {"out": "", "err": "yellow", "result": "cyan", "error": "red", "input": "bold"}


class ConsoleOutput(Message):
    def __init__(self, kind: str, text: str) -> None:
        super().__init__()
        self.kind, self.text = kind, text


class ConsoleFinished(Message):
    def __init__(self, ok: bool) -> None:
        super().__init__()
        self.ok = ok


class ConsolePanel(Vertical):
    """Output pane, status line and input box over one :class:`Interpreter`."""

    def __init__(self, session: Session, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.session = session
        self.interpreter = Interpreter(session.namespace(),
                                       lambda kind, text: self.post_message(ConsoleOutput(kind, text)),
                                       on_interrupt=self._abort_scan)
        self.transcript: list[tuple[str, str]] = []
        self._partial = {"out": "", "err": ""}

    def compose(self) -> ComposeResult:
        yield RichLog(id="console-out", wrap=True, markup=False, highlight=False, max_lines=5000,
                      min_width=20)
        yield Static("ready", id="console-status")
        yield ConsoleInput(id="console-in")

    def on_mount(self) -> None:
        self._write("out", BANNER + "\n")

    def _abort_scan(self) -> bool:
        if self.session.state in ("running", "paused"):
            self.session.abort()
            return True
        return False

    # ---- output -------------------------------------------------------------------------------

    def _write(self, kind: str, text: str) -> None:
        """Show ``text``; stdout/stderr are shown a whole line at a time."""
        self.transcript.append((kind, text))
        log = self.query_one(RichLog)
        if kind in self._partial:
            text = self._partial[kind] + text
            *lines, self._partial[kind] = text.split("\n")
            for line in lines:
                log.write(Text(line, style=STYLES[kind]))
        else:
            self._flush_partial()
            log.write(Text(text.rstrip("\n"), style=STYLES[kind]))

    def _flush_partial(self) -> None:
        for kind, rest in self._partial.items():
            if rest:
                self.query_one(RichLog).write(Text(rest, style=STYLES[kind]))
                self._partial[kind] = ""

    def on_console_output(self, message: ConsoleOutput) -> None:
        self._write(message.kind, message.text)

    @property
    def output_text(self) -> str:
        """Everything shown in the pane so far (for tests and copy)."""
        return "".join(t if k in self._partial else t.rstrip("\n") + "\n"
                       for k, t in self.transcript)

    # ---- running ------------------------------------------------------------------------------

    def on_console_input_submitted(self, message: ConsoleInput.Submitted) -> None:
        box = self.query_one(ConsoleInput)
        if box.busy:
            self.query_one("#console-status", Static).update(
                "[yellow]still running the previous input — ctrl+c interrupts it[/]")
            box.text = message.source
            return
        prompt = "\n".join(("... " if i else ">>> ") + line
                           for i, line in enumerate(message.source.split("\n")))
        self._write("input", prompt)
        box.busy = True
        self.query_one("#console-status", Static).update("[b]running…[/] ctrl+c interrupts")
        self.run_worker(lambda: self._run(message.source), thread=True, group="console",
                        exit_on_error=False)

    def _run(self, source: str) -> None:
        ok = self.interpreter.run(source)
        self.post_message(ConsoleFinished(ok))

    def on_console_finished(self, message: ConsoleFinished) -> None:
        self._flush_partial()
        self.query_one(ConsoleInput).busy = False
        self.query_one("#console-status", Static).update(
            "ready" if message.ok else "[red]the input raised an error (traceback above)[/]")

    def on_console_input_interrupt(self, message: ConsoleInput.Interrupt) -> None:
        if self.interpreter.interrupt():
            self.query_one("#console-status", Static).update("[yellow]interrupting…[/]")

    @property
    def busy(self) -> bool:
        return self.query_one(ConsoleInput).busy
