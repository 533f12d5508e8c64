"""The Rig panel: every device of the profile with its backend, connection and live status, and
the keys that drive them (connect, jog, go to, analyzer, exposure, snap, project, decode).

Safety: no navigation key (arrows, tab, home/end, page up/down) moves hardware — jogging is on
``[`` and ``]``; key repeat collapses into one move (:mod:`dotshell.tui.jog`); escape stops
every moving device at once. Prompts start from the device's current value.
"""

from __future__ import annotations

from typing import Any

from rich.console import Group
from rich.markup import escape
from rich.table import Table
from rich.text import Text
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Vertical
from textual.events import Resize
from textual.widgets import Static

from dotshell.server.describe import short_path
from dotshell.tui.jog import JogQueue
from dotshell.tui.messages import ActionDone
from dotshell.tui.redraw import DrawnWhileShown, show, update
from dotshell.tui.text import describe_status, shown_path
from dotshell.tui.widgets.choice import ChoiceScreen
from dotshell.tui.widgets.prompt import PromptScreen

ROLES = ("camera", "projector", "stage", "analyzer", "light_source")
HELP = ("[b]c[/] connect  [b]d[/] disconnect  [b][ ][/] jog ∓step  [b]+ -[/] step  "
        "[b]g[/] go to  [b]h[/] home  [b]a[/] analyzer  [b]e[/] exposure  [b]space[/] snap  "
        "[b]t[/] pattern  "
        "[b]m[/] decode map  [b]esc[/] stop")
#: Below this width the device table is stacked: one device per two lines.
STACK_BELOW = 80


class RigPanel(DrawnWhileShown, Vertical, can_focus=True):
    """Device table and rig keys; every action is a request to the server, run in a worker.
    The profile and the device table are drawn while the Rig tab is shown (from the latest
    rows when it is shown again)."""

    BINDINGS = [
        Binding("c", "connect", "Connect"),
        Binding("d", "disconnect", "Disconnect", show=False),
        Binding("left_square_bracket", "jog(-1)", "Jog −", key_display="["),
        Binding("right_square_bracket", "jog(1)", "Jog +", key_display="]"),
        Binding("plus,equals_sign", "step(2)", "Step ×2", show=False),
        Binding("minus", "step(0.5)", "Step ÷2", show=False),
        Binding("g", "goto", "Go to", show=False),
        Binding("h", "home", "Home", show=False),
        Binding("a", "analyzer", "Analyzer", show=False),
        Binding("e", "exposure", "Exposure", show=False),
        Binding("space", "snap", "Snap"),
        Binding("t", "project", "Pattern", show=False),
        Binding("m", "decode", "Decode", show=False),
    ]

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.step_deg = 5.0
        self.last_result = ""
        self.last_error = ""
        self.rows: list[dict[str, Any]] = []
        self._drawn: tuple[Any, ...] | None = None  # what the device table shows now
        self.jogs = JogQueue(lambda deg: self._do("jog", self.session.jog, deg))

    def compose(self) -> ComposeResult:
        yield Static(id="rig-title")
        yield Static(id="rig-table")
        yield Static(id="rig-result")
        yield Static(id="rig-error", classes="error")
        yield Static(HELP, id="rig-help", classes="help")

    @property
    def session(self) -> Any:
        return self.app.session  # type: ignore[attr-defined]

    # ---- display ------------------------------------------------------------------------------

    def redraw(self) -> None:
        self.show_profile()

    def show_profile(self) -> None:
        if not self.drawing():
            return
        p = self.session.profile
        title = (f"[b]{escape(p['name'])}[/]  {escape(shown_path(p['source']))}" if p else
                 "[b]no profile loaded[/] — press ctrl+o to pick one")
        show(self.query_one("#rig-title", Static), f"{title}   jog step {self.step_deg:g}°")
        self.show_rows(self.rows)

    def show_rows(self, rows: list[dict[str, Any]]) -> None:
        """Draw the device table, unless it shows these rows this way already (the app
        calls this on every state change and each time the tab is shown)."""
        self.rows = rows
        if not self.drawing():
            return
        projected = self.session.projected
        stacked = self.app.size.width < STACK_BELOW
        if self._drawn == (stacked, projected, rows):
            return
        self._drawn = (stacked, projected, rows)
        if stacked:
            update(self.query_one("#rig-table", Static), self._stacked(rows, projected))
            return
        table = Table(box=None, expand=True, pad_edge=False, header_style="bold")
        table.add_column("device", no_wrap=True)
        table.add_column("backend", no_wrap=True)
        table.add_column("state", no_wrap=True)
        table.add_column("status", ratio=1)
        for row in rows:
            state = Text("connected", "green") if row["connected"] else Text("closed", "dim")
            status = describe_status(row["role"], row["status"], projected)
            table.add_row(row["role"], row["backend"], state,
                          Text(status, "bold red" if status.startswith("error") else ""))
        absent = self._absent(rows)
        note = Text(f"not in profile: {', '.join(absent)}" if rows and absent else "", "dim")
        update(self.query_one("#rig-table", Static), Group(table, note))

    def _stacked(self, rows: list[dict[str, Any]], projected: str | None) -> Text:
        out = Text()
        for row in rows:
            mark = ("● ", "green") if row["connected"] else ("○ ", "dim")
            out.append(*mark)
            out.append(f"{row['role']} ", "bold")
            out.append(f"{row['backend']}\n", "dim")
            status = describe_status(row["role"], row["status"], projected)
            out.append(f"  {status}\n" if status else "",
                       "bold red" if status.startswith("error") else "")
        absent = self._absent(rows)
        if rows and absent:
            out.append(f"not in profile: {', '.join(absent)}", "dim")
        return out

    @staticmethod
    def _absent(rows: list[dict[str, Any]]) -> list[str]:
        configured = {r["role"] for r in rows}
        return [r for r in ROLES if r not in configured]

    def on_resize(self, event: Resize) -> None:
        self.show_rows(self.rows)

    def show_result(self, text: str, error: str = "") -> None:
        self.last_result, self.last_error = text, error
        show(self.query_one("#rig-result", Static), escape(text))
        show(self.query_one("#rig-error", Static), escape(error))

    def on_action_done(self, message: ActionDone) -> None:
        if message.label == "jog":
            self.jogs.done()
        if message.label == "patterns" and not message.error:
            return  # the chooser opens
        if message.error:
            self.show_result("", f"{message.label}: {message.error}")
        else:
            text = self._describe(message.label, message.result)
            if message.label == "snap" and not self.session.projected:
                text += ("\nthe projector shows no pattern, so the frame is dark: t projects "
                         "one (white lights the sample)")
            self.show_result(text)

    @staticmethod
    def _describe(label: str, result: Any) -> str:
        if label == "snap":
            return (f"snap at {result['angle_deg']:.2f}°: {result['width']}×{result['height']} "
                    f"{result['dtype']}, mean {result['mean']:.0f} DN → "
                    f"{short_path(result['path'])}")
        if label == "decode map":
            pct = 100.0 * result["decoded_pixels"] / max(result["total_pixels"], 1)
            return (f"decoded {result['decoded_pixels']} of {result['total_pixels']} pixels "
                    f"({pct:.1f} %) → {short_path(result['preview'])}")
        if label == "stop":
            return {"paused": "scan paused by the stop key: p resumes it, x aborts it",
                    "stopping": "the scan is stopping already (aborted)"}.get(
                        result, "stopped: every device that can move")
        if label in ("jog", "go to", "home") and isinstance(result, (int, float)):
            return f"stage at {result:.2f}°"
        if label == "connect" and isinstance(result, dict):
            return f"connected: {', '.join(result)}"
        return f"{label}: done" if result is None else f"{label}: {result}"

    def current(self, role: str, key: str, fallback: float) -> float:
        """A device's current value from the last status (``fallback`` when unknown)."""
        for row in self.rows:
            if row["role"] == role and isinstance(row["status"].get(key), (int, float)):
                return float(row["status"][key])
        return fallback

    # ---- keys ---------------------------------------------------------------------------------

    def _do(self, label: str, fn: Any, *args: Any) -> None:
        self.show_result(f"{label}…")
        self.app.run_session_action(label, fn, *args, reply_to=self)  # type: ignore[attr-defined]

    def action_connect(self) -> None:
        self._do("connect", self.session.connect)

    def action_disconnect(self) -> None:
        self._do("disconnect", self.session.disconnect)

    def action_jog(self, direction: int) -> None:
        self.jogs.press(direction * self.step_deg)

    def stop(self) -> None:
        """The stop key: forget pending jogs and halt — a scan pauses before its next frame,
        otherwise every moving device stops (never an abort)."""
        self.jogs.cancel()
        self._do("stop", self.session.halt)

    def action_step(self, factor: float) -> None:
        self.step_deg = min(180.0, max(0.125, self.step_deg * factor))
        self.show_profile()

    def _ask(self, question: str, value: float, label: str, fn: Any) -> None:
        def answered(text: str | None) -> None:
            if text is None:
                return
            try:
                number = float(text)
            except ValueError:
                self.show_result("", f"{label}: {text!r} is not a number")
                return
            self._do(label, fn, number)

        self.app.push_screen(PromptScreen(question, f"{value:g}"), answered)

    def action_goto(self) -> None:
        self._ask("Stage angle (degrees, absolute):", self.current("stage", "angle_deg", 0.0),
                  "go to", self.session.move_to)

    def action_home(self) -> None:
        self._do("home", self.session.home)

    def action_analyzer(self) -> None:
        self._ask("Analyzer angle (degrees):", self.current("analyzer", "angle_deg", 0.0),
                  "analyzer", self.session.set_analyzer)

    def action_exposure(self) -> None:
        p = self.session.profile
        self._ask("Camera exposure (ms):",
                  self.current("camera", "exposure_ms", p["exposure_ms"] if p else 20.0),
                  "exposure", self.session.set_exposure)

    def action_snap(self) -> None:
        self._do("snap", self.session.snap)

    def action_decode(self) -> None:
        self._do("decode map", self.session.decode)

    def action_project(self) -> None:
        def listed(names: list[str]) -> None:
            def chosen(name: str | None) -> None:
                if name:
                    self._do("project", self.session.project, name)

            self.app.push_screen(ChoiceScreen("Project which pattern?", names,
                                              self.session.projected), chosen)

        self.app.run_session_action("patterns", self.session.patterns,  # type: ignore[attr-defined]
                                    then=listed, reply_to=self)
