"""The Scan panel: the profile's scan, start / pause / resume / abort, progress per view and
frame with ETA, the current pipeline step, the result, and errors in place. View numbers are
1-based, as on the progress bar. Aborting always asks first; the stop key (esc) only pauses a scan.
"""

from __future__ import annotations

import time
from typing import Any

from rich.markup import escape
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.widgets import Label, ProgressBar, Static

from dotshell.server.progress import ScanTracker, format_seconds
from dotshell.tui.messages import ActionDone
from dotshell.tui.redraw import DrawnWhileShown, show
from dotshell.tui.text import shown_path
from dotshell.tui.widgets.confirm import ConfirmScreen
from dotshell.tui.widgets.prompt import PromptScreen

HELP = ("[b]s[/] start  [b]p[/] pause / resume  [b]x[/] abort (asks; frames are kept)  "
        "[b]esc[/] stop motion (pauses a scan)   settings: [b]v[/] views  [b]e[/] exposure  "
        "[b]n[/] analyzer angles  [b]o[/] output folder")
STATE_STYLE = {"running": "green", "paused": "yellow", "stopping": "yellow", "completed": "green",
               "aborted": "yellow", "failed": "bold red"}


class ScanPanel(DrawnWhileShown, Vertical, can_focus=True):
    """Scan controls and progress, redrawn from the app's :class:`ScanTracker` (while the Scan
    tab is shown; from the latest progress when it is shown again)."""

    BINDINGS = [
        Binding("s", "start", "Start scan"),
        Binding("v", "views", "Views", show=False),
        Binding("e", "exposure", "Exposure", show=False),
        Binding("n", "analyzer_angles", "Analyzer angles", show=False),
        Binding("o", "out_dir", "Output folder", show=False),
        Binding("p", "app.pause", "Pause/resume"),  # p and x are the app's (every tab): shown
        Binding("x", "app.abort", "Abort"),  # here in the footer too
    ]

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.failure = ""

    def compose(self) -> ComposeResult:
        yield Static(id="scan-plan")
        yield Static(id="scan-state")
        with Horizontal(classes="bar-row"):
            yield Label("views ", classes="bar-label")
            # a total from the start: a bar without one animates (15 redraws a second, also
            # while the tab is hidden and before the panel first draws)
            yield ProgressBar(total=1, id="views-bar", show_eta=False)
            yield Label(id="views-count", classes="bar-count")
        with Horizontal(classes="bar-row"):
            yield Label("frames", classes="bar-label")
            yield ProgressBar(total=1, id="frames-bar", show_eta=False)
            yield Label(id="frames-count", classes="bar-count")
        yield Static(id="scan-result")
        yield Static(id="scan-error", classes="error")
        yield Static(HELP, classes="help")

    @property
    def session(self) -> Any:
        return self.app.session  # type: ignore[attr-defined]

    def redraw(self) -> None:
        self.show_tracker(self.app.tracker, time.time())  # type: ignore[attr-defined]

    def show_tracker(self, t: ScanTracker, now_s: float) -> None:
        if not self.drawing():
            return
        self._show_plan()
        session = self.session
        state = session.session_state if session.scanning else t.shown_status
        style = STATE_STYLE.get(state, "")
        line = f"state [{style}]{state}[/]" if style else f"state {state}"
        if t.active or session.scanning:
            view = f"{t.current_view + 1}/{t.n_views}" if t.current_view >= 0 else "…"
            line += (f"   step [b]{escape(t.step or '…')}[/]   view {view}"
                     f"   elapsed {format_seconds(t.active_seconds(now_s))}"
                     f"   ETA {t.eta_text(now_s)}")
        show(self.query_one("#scan-state", Static), line)
        self.query_one("#views-bar", ProgressBar).update(total=max(t.n_views, 1),
                                                         progress=t.views_done)
        self.query_one("#frames-bar", ProgressBar).update(total=max(t.frames_total, 1),
                                                          progress=t.frames_done)
        show(self.query_one("#views-count", Label), f"{t.views_done}/{t.n_views}")
        show(self.query_one("#frames-count", Label), f"{t.frames_done}/{t.frames_total}")
        show(self.query_one("#scan-result", Static), self._result(t))
        error = self.failure or (t.error if t.shown_status == "failed" else "")
        if t.shown_status == "failed" and t.status == "completed":
            error = error or "the scan produced no points: check the previews, the lighting, " \
                             "the calibration and [processing.roi]."
        show(self.query_one("#scan-error", Static), escape(error))

    def _show_plan(self) -> None:
        p = self.session.profile
        if p is None:
            text = "no profile loaded — ctrl+o"
        else:
            out_dir = shown_path(self.session.state["out_dir"])
            pdi = (f", PDI analyzer {' / '.join(f'{a:g}°' for a in p['pdi_angles_deg'])}"
                   if p.get("pdi") else "")
            text = (f"[b]{escape(p['name'])}[/]: {p['views']} views, exposure "
                    f"{p['exposure_ms']:g} ms{pdi}, coding {escape(p['coding'])} → "
                    f"{escape(out_dir)}/")
        show(self.query_one("#scan-plan", Static), text)

    @staticmethod
    def _result(t: ScanTracker) -> str:
        if not t.run_dir:
            return ""
        text = f"run {escape(shown_path(t.run_dir))}"
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

    def _do(self, label: str, fn: Any) -> None:
        self.app.run_session_action(label, fn, reply_to=self)  # type: ignore[attr-defined]

    def action_start(self) -> None:
        self.failure = ""
        self._do("scan", self.session.scan)

    def action_pause(self) -> None:
        if not self.session.scanning:
            return
        if self.session.session_state == "paused":
            self._do("resume", self.session.resume)
        else:
            self._do("pause", self.session.pause)

    def action_abort(self) -> None:
        """Abort the scan, after a yes (from any tab, the palette or ``x``); a watcher is told
        that only the client in control may abort."""
        tracker: ScanTracker = self.app.tracker  # type: ignore[attr-defined]
        if not self.session.scanning:
            return
        if not self.session.in_control:
            self.failure = ("abort: only the front end in control may abort the scan (ctrl+t "
                            "takes control); esc pauses it")
            self.app.notify(self.failure, severity="warning")
            self.app.show_scan()  # type: ignore[attr-defined]
            return
        running_s = tracker.active_seconds(time.time())

        def answer(yes: bool | None) -> None:
            if yes:
                self._do("abort", self.session.abort)

        self.app.push_screen(ConfirmScreen(
            f"The scan has run for {format_seconds(running_s)}. Abort it?\nFrames captured so "
            "far are kept and the run is marked aborted.", yes="Abort the scan",
            no="Keep scanning"), answer)

    # ---- the next scan's settings ---------------------------------------------------------------

    def _setting(self, question: str, value: str, parse: Any, label: str,
                 send: Any) -> None:
        """Ask for one setting (starting from its value now), parse it and send it; a value
        that does not parse, or that the server refuses, is said in the error line."""
        if self.session.profile is None:
            self.failure = f"{label}: no profile loaded — ctrl+o"
            self.app.show_scan()  # type: ignore[attr-defined]
            return

        def answered(text: str | None) -> None:
            if text is None:
                return
            try:
                parsed = parse(text)
            except ValueError as exc:
                self.failure = f"{label}: {text!r} is not {exc}"
                self.app.show_scan()  # type: ignore[attr-defined]
                return
            self.failure = ""
            self._do(label, lambda: send(parsed))

        self.app.push_screen(PromptScreen(question, value), answered)

    def action_views(self) -> None:
        p = self.session.profile or {}
        self._setting("Views (equally spaced over 360°):", str(p.get("views", "")),
                      _positive_int, "views",
                      lambda n: self.session.configure(views=n))

    def action_exposure(self) -> None:
        """The same as the Rig tab's e: the camera now (when connected) and the scans."""
        p = self.session.profile or {}
        self._setting("Camera exposure (ms), for the camera now and the scans:",
                      f"{p.get('exposure_ms', 20.0):g}", _positive_float, "exposure",
                      self.session.set_exposure)

    def action_analyzer_angles(self) -> None:
        p = self.session.profile or {}
        angles = p.get("pdi_angles_deg") or [0.0, 90.0]
        note = "" if p.get("pdi") else " (used when scan.pdi is on; it is off)"
        self._setting(f"PDI analyzer angles, parallel and perpendicular (degrees){note}:",
                      ", ".join(f"{a:g}" for a in angles), _two_angles, "analyzer angles",
                      lambda a: self.session.configure(pdi_angles_deg=a))

    def action_out_dir(self) -> None:
        self._setting("Output folder (runs are made inside it):",
                      shown_path(self.session.state.get("out_dir", "runs")), _folder,
                      "output folder", lambda d: self.session.configure(out_dir=d))

    def on_action_done(self, message: ActionDone) -> None:
        if message.label == "scan":
            self.failure = message.error
        elif message.error:
            self.failure = f"{message.label}: {message.error}"
        self.app.show_scan()  # type: ignore[attr-defined]


def _positive_int(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise ValueError("a whole number") from None
    if n < 1:
        raise ValueError("a number of views (1 or more)")
    return n


def _positive_float(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise ValueError("a number") from None
    if x <= 0:
        raise ValueError("a positive number")
    return x


def _two_angles(text: str) -> list[float]:
    parts = [t for t in text.replace(",", " ").split() if t]
    try:
        angles = [float(t) for t in parts]
    except ValueError:
        raise ValueError("two angles in degrees, e.g. 0, 90") from None
    if len(angles) != 2:
        raise ValueError("two angles in degrees (parallel, perpendicular), e.g. 0, 90")
    return angles


def _folder(text: str) -> str:
    if not text.strip():
        raise ValueError("a folder")
    return text.strip()
