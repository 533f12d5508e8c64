"""The Scan panel: the profile's scan, start / pause / resume / abort, progress per view and
frame with ETA, the current pipeline step, the result, and errors in place."""

from __future__ import annotations

from typing import Any

from rich.markup import escape
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.widgets import Label, ProgressBar, Static

from dotshell.console import Session
from dotshell.tui.messages import ActionDone
from dotshell.tui.progress import ScanTracker, format_seconds
from dotshell.tui.text import short_path

HELP = "[b]s[/] start  [b]p[/] pause / resume  [b]x[/] abort (frames are kept)"
STATE_STYLE = {"running": "green", "paused": "yellow", "stopping": "yellow", "completed": "green",
               "aborted": "yellow", "failed": "red"}


class ScanPanel(Vertical, can_focus=True):
    """Scan controls and progress, redrawn from the app's :class:`ScanTracker`."""

    BINDINGS = [
        Binding("s", "start", "Start scan"),
        Binding("p", "pause", "Pause/resume"),
        Binding("x", "abort", "Abort"),
    ]

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.failure = ""

    def compose(self) -> ComposeResult:
        yield Static(id="scan-plan")
        yield Static(id="scan-state")
        with Horizontal(classes="bar-row"):
            yield Label("views ", classes="bar-label")
            yield ProgressBar(id="views-bar", show_eta=False)
            yield Label(id="views-count", classes="bar-count")
        with Horizontal(classes="bar-row"):
            yield Label("frames", classes="bar-label")
            yield ProgressBar(id="frames-bar", show_eta=False)
            yield Label(id="frames-count", classes="bar-count")
        yield Static(id="scan-result")
        yield Static(id="scan-error", classes="error")
        yield Static(HELP, classes="help")

    @property
    def session(self) -> Session:
        return self.app.session  # type: ignore[attr-defined]

    def show_tracker(self, t: ScanTracker, session: Session, now_s: float) -> None:
        self._show_plan(session)
        state = session.state if session.scanning else t.status
        style = STATE_STYLE.get(state, "")
        line = f"state [{style}]{state}[/]" if style else f"state {state}"
        if t.active or session.scanning:
            line += (f"   step [b]{escape(t.step or '…')}[/]   view {max(t.current_view, 0)}"
                     f"   elapsed {format_seconds(t.active_seconds(now_s))}"
                     f"   ETA {format_seconds(t.eta_s(now_s))}")
        self.query_one("#scan-state", Static).update(line)
        self.query_one("#views-bar", ProgressBar).update(total=max(t.n_views, 1),
                                                         progress=t.views_done)
        self.query_one("#frames-bar", ProgressBar).update(total=max(t.frames_total, 1),
                                                          progress=t.frames_done)
        self.query_one("#views-count", Label).update(f"{t.views_done}/{t.n_views}")
        self.query_one("#frames-count", Label).update(f"{t.frames_done}/{t.frames_total}")
        self.query_one("#scan-result", Static).update(self._result(t))
        error = self.failure or (t.error if t.status == "failed" else "")
        self.query_one("#scan-error", Static).update(escape(error))

    def _show_plan(self, session: Session) -> None:
        p = session.profile
        if p is None:
            text = "no profile loaded — ctrl+o"
        else:
            scan = p.data["scan"]
            text = (f"[b]{escape(p.name)}[/]: {len(p.angles_deg())} views, exposure "
                    f"{scan['exposure_ms']:g} ms, coding {escape(p.role('coding')['backend'])} "
                    f"→ {escape(short_path(session.out_dir))}/")
        self.query_one("#scan-plan", Static).update(text)

    @staticmethod
    def _result(t: ScanTracker) -> str:
        if not t.run_dir:
            return ""
        text = f"run {escape(short_path(t.run_dir))}"
        if t.points:
            text += f"   {t.points} points in {t.views_reconstructed} views"
        s = t.summary
        if "mean_rel_error_pct" in s:
            text += (f"\nradius error {s['mean_rel_error_pct']:.2f} % ± "
                     f"{s.get('std_rel_error_pct', 0):.2f} %")
            if "coverage_pct" in s:
                text += f", coverage {s['coverage_pct']:.1f} %"
        return text

    # ---- keys ---------------------------------------------------------------------------------

    def action_start(self) -> None:
        self.failure = ""
        self.app.start_scan(reply_to=self)  # type: ignore[attr-defined]

    def action_pause(self) -> None:
        if self.session.state == "paused":
            self.session.resume()
        else:
            self.session.pause()
        self.app.show_scan()  # type: ignore[attr-defined]

    def action_abort(self) -> None:
        self.session.abort()
        self.app.show_scan()  # type: ignore[attr-defined]

    def on_action_done(self, message: ActionDone) -> None:
        if message.label == "scan":
            self.failure = message.error
            self.app.show_scan()  # type: ignore[attr-defined]
