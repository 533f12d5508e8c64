"""The Console panel: the Python console of the rig server, bound to its live session
(``rig``, ``profile``, ``run``, ``scan()``, ``np`` and the rest of
:meth:`dotshell.session.console.Session.namespace`). Input is sent to the server and runs there;
output, results, tracebacks and ``input()`` prompts come back as they happen, to every attached
front end."""

from __future__ import annotations

from typing import Any

from rich.markup import escape
from rich.text import Text
from textual.app import ComposeResult
from textual.containers import Vertical
from textual.widgets import Static

from dotshell.tui.messages import ActionDone
from dotshell.tui.redraw import show
from dotshell.tui.text import copy_text
from dotshell.tui.widgets.console_input import ConsoleInput
from dotshell.tui.widgets.reflow_log import ReflowLog

BANNER = ("Python console on the live session: rig, profile, run, session, np, dotshell; "
          "connect(), jog(deg), move_to(deg), home(), snap(), project(name), patterns(), "
          "decode(), scan(), pause(), resume(), abort(), stop(). Enter runs, a blank line ends a "
          "block, "
          "↑/↓ history, Tab completes, ctrl+c interrupts; input() and help() ask here.")
STYLES = {"out": "", "err": "yellow", "result": "cyan", "error": "bold red", "input": "bold",
          "note": "dim", "log": "italic"}
READY = "ready"


class ConsolePanel(Vertical):
    """Output pane, status line and input box; the interpreter runs in the server."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.transcript: list[tuple[str, str]] = []
        self._partial = {"out": "", "err": "", "log": ""}
        self._sent = ""  # the last input sent to the server

    def compose(self) -> ComposeResult:
        output = ReflowLog(id="console-out")
        output.can_focus = False  # the input keeps the focus (page up/down scroll this)
        yield output
        yield Static(READY, id="console-status")
        yield ConsoleInput(id="console-in")

    def on_mount(self) -> None:
        self.write("note", BANNER + "\n")

    @property
    def session(self) -> Any:
        return self.app.session  # type: ignore[attr-defined]

    @property
    def box(self) -> ConsoleInput:
        return self.query_one(ConsoleInput)

    def _status(self, markup: str) -> None:
        show(self.query_one("#console-status", Static), markup)

    # ---- output -------------------------------------------------------------------------------

    def write(self, kind: str, text: str) -> None:
        """Show ``text``; stdout/stderr are shown a whole line at a time."""
        self.transcript.append((kind, text))
        log = self.query_one(ReflowLog)
        if kind in self._partial:
            text = self._partial[kind] + text
            *lines, self._partial[kind] = text.split("\n")
            for line in lines:
                log.add(Text(line, style=STYLES[kind]))
        else:
            self._flush_partial()
            if kind == "input":
                text = "\n".join(("... " if i else ">>> ") + line
                                 for i, line in enumerate(text.split("\n")))
            log.add(Text(text.rstrip("\n"), style=STYLES.get(kind, "")))

    def _flush_partial(self) -> None:
        for kind, rest in self._partial.items():
            if rest:
                self.query_one(ReflowLog).add(Text(rest, style=STYLES[kind]))
                self._partial[kind] = ""

    @property
    def output_text(self) -> str:
        """Everything shown in the pane so far (for tests and copy)."""
        return self._joined(self.transcript)

    def _joined(self, entries: list[tuple[str, str]]) -> str:
        return "".join(t if k in self._partial else t.rstrip("\n") + "\n" for k, t in entries)

    # ---- what the server says -----------------------------------------------------------------

    def handle(self, message: dict[str, Any]) -> None:
        kind = message.get("type")
        if kind == "console":
            if message["kind"] == "input":
                self._set_busy(True)
            self.write(message["kind"], message["text"])
        elif kind == "console_input":
            self.box.waiting_prompt = message.get("prompt", "")
            prompt = message.get("prompt") or ""
            self._status(f"[b]input()[/] {escape(prompt)}   — Enter sends the line, ctrl+d ends "
                         "the input, ctrl+c interrupts")
        elif kind == "console_done":
            self._flush_partial()
            self.box.waiting_prompt = None
            self._set_busy(False)
            self._status(READY if message.get("ok") else
                         "[bold red]the input raised an error (traceback above)[/]")

    def _set_busy(self, busy: bool) -> None:
        self.box.busy = busy
        if busy and self.box.waiting_prompt is None:
            self._status("[b]running…[/] ctrl+c interrupts")

    @property
    def busy(self) -> bool:
        return self.box.busy

    def replay(self, transcript: list[dict[str, Any]], console: dict[str, Any]) -> None:
        """A front end attaching: show what the console showed before (the server's bounded
        transcript), then its true state — busy while an input (a ``scan()``) still runs,
        waiting when it asks with ``input()``."""
        if transcript:
            self.write("note", "— the console so far (from the server) —\n")
        for message in transcript:
            self.handle(message)
        busy = bool(console.get("busy"))
        prompt = console.get("prompt")
        if prompt is not None and busy:
            self.handle({"type": "console_input", "prompt": prompt})
            self.box.busy = True
        elif busy:
            self.box.waiting_prompt = None
            self._set_busy(True)
        elif self.box.busy:  # the transcript ended inside an input that has finished since
            self.box.busy = False
            self._status(READY)

    # ---- input --------------------------------------------------------------------------------

    def _request(self, label: str, fn: Any, *args: Any) -> None:
        self.app.run_session_action(label, fn, *args, reply_to=self)  # type: ignore[attr-defined]

    def on_console_input_submitted(self, message: ConsoleInput.Submitted) -> None:
        if self.box.busy:
            self._refused(message.source, "still running the previous input — it was not "
                          "sent; Enter again when it ends, ctrl+c interrupts it")
            return
        self.box.busy = True
        self._sent = message.source
        self._request("console", self.session.console_run, message.source)

    def _refused(self, source: str, why: str) -> None:
        """Input that did not run stays in the box (never lost), and the status says why."""
        if not self.box.text.strip():
            self.box.text = source
            self.box.move_cursor(self.box.document.end)
        self._status(f"[b reverse] not run [/] [yellow]{escape(why)}[/]")

    def on_console_input_reply(self, message: ConsoleInput.Reply) -> None:
        self.box.waiting_prompt = None
        self._status("[b]running…[/] ctrl+c interrupts")
        self._request("console reply", self.session.console_reply, message.line)

    def on_console_input_interrupt(self, message: ConsoleInput.Interrupt) -> None:
        self._status("[yellow]interrupting…[/]")
        self._request("interrupt", self.session.console_interrupt)

    def last_output(self) -> str:
        """What the last input printed and returned (its echo excluded)."""
        cut = max((i for i, (k, _) in enumerate(self.transcript) if k == "input"), default=-1)
        return self._joined([(k, t) for k, t in self.transcript[cut + 1:] if k != "note"])

    def on_console_input_copy_output(self, message: ConsoleInput.CopyOutput) -> None:
        text = self.last_output()
        if not text.strip():
            self._status("[yellow]nothing to copy: the last input printed nothing[/]")
            return
        copy_text(self.app, text, "the last input's output")

    def on_console_input_page(self, message: ConsoleInput.Page) -> None:
        output = self.query_one(ReflowLog)
        (output.scroll_page_up if message.up else output.scroll_page_down)(animate=False)

    def on_console_input_complete_request(self, message: ConsoleInput.CompleteRequest) -> None:
        self._request("complete", self.session.complete, message.text)

    def on_action_done(self, message: ActionDone) -> None:
        if message.error:
            if message.label == "console":
                # refused by the server (another input runs, another front end controls):
                # the input is put back; busy stays what the server says
                self.box.busy = bool((self.session.state.get("console") or {}).get("busy"))
                self._refused(self._sent, message.error)
                return
            self._status(f"[bold red]{escape(message.label)}: {escape(message.error)}[/]")
        elif message.label == "complete":
            token, matches = message.result["token"], message.result["matches"]
            self.box.apply_completion(token, matches)
            if len(matches) > 1:
                self.write("note", "  ".join(matches))
