"""The Rig panel: every device of the profile with its backend, connection and live status, and
the keys that drive them (connect, jog, analyzer, exposure, snap, project, decode)."""

from __future__ import annotations

from typing import Any

from rich.markup import escape
from rich.table import Table
from rich.text import Text
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Vertical
from textual.widgets import Static

from dotshell.console import DecodeResult, Session, Snapshot
from dotshell.profile import DEVICE_ROLES
from dotshell.tui.messages import ActionDone
from dotshell.tui.text import describe_status, short_path
from dotshell.tui.widgets.choice import ChoiceScreen
from dotshell.tui.widgets.prompt import PromptScreen

HELP = ("[b]c[/] connect  [b]d[/] disconnect  [b]←/→[/] jog ∓step  [b]+/-[/] step  "
        "[b]g[/] go to angle  [b]a[/] analyzer  [b]e[/] exposure  [b]space[/] snap  "
        "[b]p[/] project  [b]m[/] decode map")


class RigPanel(Vertical, can_focus=True):
    """Device table and rig keys; every action runs in a worker via the app."""

    BINDINGS = [
        Binding("c", "connect", "Connect"),
        Binding("d", "disconnect", "Disconnect", show=False),
        Binding("left", "jog(-1)", "Jog −"),
        Binding("right", "jog(1)", "Jog +"),
        Binding("plus,equals_sign", "step(2)", "Step ×2", show=False),
        Binding("minus", "step(0.5)", "Step ÷2", show=False),
        Binding("g", "goto", "Go to", show=False),
        Binding("a", "analyzer", "Analyzer", show=False),
        Binding("e", "exposure", "Exposure", show=False),
        Binding("space", "snap", "Snap"),
        Binding("p", "project", "Project"),
        Binding("m", "decode", "Decode", show=False),
    ]

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.step_deg = 5.0
        self.last_result = ""
        self.last_error = ""

    def compose(self) -> ComposeResult:
        yield Static(id="rig-title")
        yield Static(id="rig-table")
        yield Static(id="rig-result")
        yield Static(id="rig-error", classes="error")
        yield Static(HELP, id="rig-help", classes="help")

    @property
    def session(self) -> Session:
        return self.app.session  # type: ignore[attr-defined]

    # ---- display ------------------------------------------------------------------------------

    def show_profile(self, session: Session) -> None:
        p = session.profile
        title = (f"[b]{escape(p.name)}[/]  {escape(short_path(p.source))}" if p else
                 "[b]no profile loaded[/] — press ctrl+o to pick one")
        self.query_one("#rig-title", Static).update(f"{title}   jog step {self.step_deg:g}°")
        self.show_rows([], session)

    def show_rows(self, rows: list[dict[str, Any]], session: Session) -> None:
        table = Table(box=None, expand=True, pad_edge=False, header_style="bold")
        table.add_column("device", no_wrap=True)
        table.add_column("backend", no_wrap=True)
        table.add_column("state", no_wrap=True)
        table.add_column("status", ratio=1)
        for row in rows:
            state = Text("connected", "green") if row["connected"] else Text("closed", "dim")
            status = describe_status(row["role"], row["status"], session.projected)
            style = "red" if status.startswith("error") else ""
            table.add_row(row["role"], row["backend"], state, Text(status, style))
        configured = {r["role"] for r in rows}
        absent = [r for r in DEVICE_ROLES if r not in configured]
        if rows and absent:
            table.add_row(Text(", ".join(absent), "dim"), Text("—", "dim"),
                          Text("not in profile", "dim"), "")
        self.query_one("#rig-table", Static).update(table)

    def show_result(self, text: str, error: str = "") -> None:
        self.last_result, self.last_error = text, error
        self.query_one("#rig-result", Static).update(escape(text))
        self.query_one("#rig-error", Static).update(escape(error))

    def on_action_done(self, message: ActionDone) -> None:
        if message.error:
            self.show_result("", f"{message.label}: {message.error}")
        else:
            self.show_result(self._describe(message.label, message.result))

    def _describe(self, label: str, result: Any) -> str:
        if isinstance(result, Snapshot):
            f = result.frame
            return (f"snap at {result.angle_deg:.2f}°: {f.shape[1]}×{f.shape[0]} {f.dtype}, "
                    f"mean {float(f.mean()):.0f} DN → {short_path(result.path)}")
        if isinstance(result, DecodeResult):
            pct = 100.0 * result.decoded_pixels / max(result.total_pixels, 1)
            return (f"decoded {result.decoded_pixels} of {result.total_pixels} pixels "
                    f"({pct:.1f} %) → {short_path(result.preview)}")
        if label in ("jog", "go to"):
            return f"stage at {result:.2f}°"
        if isinstance(result, dict) and label == "connect":
            return f"connected: {', '.join(result)}"
        return f"{label}: done" if result is None else f"{label}: {result}"

    # ---- keys ---------------------------------------------------------------------------------

    def _do(self, label: str, fn, *args: Any) -> None:
        self.show_result(f"{label}…")
        self.app.run_session_action(label, fn, *args, reply_to=self)  # type: ignore[attr-defined]

    def action_connect(self) -> None:
        self._do("connect", self.session.connect)

    def action_disconnect(self) -> None:
        self._do("disconnect", self.session.disconnect)

    def action_jog(self, direction: int) -> None:
        self._do("jog", self.session.jog, direction * self.step_deg)

    def action_step(self, factor: float) -> None:
        self.step_deg = min(180.0, max(0.125, self.step_deg * factor))
        self.show_profile(self.session)
        self.app.refresh_status()  # type: ignore[attr-defined]

    def _ask(self, question: str, value: str, label: str, fn) -> None:
        def answered(text: str | None) -> None:
            if text is None:
                return
            try:
                number = float(text)
            except ValueError:
                self.show_result("", f"{label}: {text!r} is not a number")
                return
            self._do(label, fn, number)

        self.app.push_screen(PromptScreen(question, value), answered)

    def action_goto(self) -> None:
        self._ask("Stage angle (degrees, absolute):", "0", "go to", self.session.move_to)

    def action_analyzer(self) -> None:
        self._ask("Analyzer angle (degrees):", "0", "analyzer", self.session.set_analyzer)

    def action_exposure(self) -> None:
        self._ask("Camera exposure (ms):", "20", "exposure", self.session.set_exposure)

    def action_snap(self) -> None:
        self._do("snap", self.session.snap)

    def action_decode(self) -> None:
        self._do("decode", self.session.decode)

    def action_project(self) -> None:
        try:
            names = self.session.patterns()
        except Exception as exc:  # no profile / coding plugin failure: say so in place
            self.show_result("", f"project: {exc}")
            return

        def chosen(name: str | None) -> None:
            if name:
                self._do("project", self.session.project, name)

        self.app.push_screen(ChoiceScreen("Project which pattern?", names,
                                          self.session.projected), chosen)
