"""``dotshell tui``: the Textual app. It owns one :class:`~dotshell.console.Session`, forwards
the session's events to the panels as messages, and runs every session action (device I/O,
scans, profile loading) in worker threads so the UI never waits on hardware.

Layout: a header, a tabbed body (Rig, Scan, Preview, Log, Console), the footer with the keys;
from 100 columns on a summary sidebar shows the rig and the scan next to any tab.
"""

from __future__ import annotations

import time
import traceback
from typing import Any, Callable, TypeVar

from textual.app import App, ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal
from textual.widget import Widget
from textual.widgets import Footer, Header, TabbedContent, TabPane

from dotshell.console import Session
from dotshell.errors import DotshellError
from dotshell.events import Message
from dotshell.tui.messages import ActionDone, DeviceRows, SessionEvent
from dotshell.tui.progress import ScanTracker
from dotshell.tui.text import short_path
from dotshell.tui.widgets.confirm import ConfirmScreen
from dotshell.tui.widgets.console_panel import ConsolePanel
from dotshell.tui.widgets.log_panel import LogPanel
from dotshell.tui.widgets.plugins_screen import PluginsScreen
from dotshell.tui.widgets.preview_panel import PreviewPanel
from dotshell.tui.widgets.profile_picker import ProfilePicker
from dotshell.tui.widgets.rig_panel import RigPanel
from dotshell.tui.widgets.scan_panel import ScanPanel
from dotshell.tui.widgets.summary import Summary

W = TypeVar("W", bound=Widget)
TABS = ("rig", "scan", "preview", "log", "console")


class DotshellApp(App):
    """The instrument shell's terminal UI over one session."""

    TITLE = "dotshell"
    CSS_PATH = "app.tcss"
    HORIZONTAL_BREAKPOINTS = [(0, "-narrow"), (100, "-wide")]
    BINDINGS = [
        Binding("ctrl+q", "quit", "Quit", priority=True),
        Binding("ctrl+o", "pick_profile", "Profile"),
        Binding("ctrl+g", "plugins", "Plugins"),
        *(Binding(f"f{i + 2}", f"show_tab('{tab}')", tab.title(), show=False)
          for i, tab in enumerate(TABS)),
    ]

    def __init__(self, session: Session, status_interval_s: float = 0.5) -> None:
        super().__init__()
        self.session = session
        self.tracker = ScanTracker()
        self.status_interval_s = status_interval_s
        self._unsubscribe: Callable[[], None] | None = None
        self._quitting = False

    # ---- layout -------------------------------------------------------------------------------

    def compose(self) -> ComposeResult:
        yield Header(show_clock=False)
        with Horizontal(id="body"):
            yield Summary(id="summary")
            with TabbedContent(id="tabs", initial="rig"):
                with TabPane("Rig", id="rig"):
                    yield RigPanel(id="rig-panel")
                with TabPane("Scan", id="scan"):
                    yield ScanPanel(id="scan-panel")
                with TabPane("Preview", id="preview"):
                    yield PreviewPanel(id="preview-panel")
                with TabPane("Log", id="log"):
                    yield LogPanel(id="log-panel")
                with TabPane("Console", id="console"):
                    yield ConsolePanel(self.session, id="console-panel")
        yield Footer()

    def on_mount(self) -> None:
        self._unsubscribe = self.session.bus.subscribe(
            lambda ev: self.post_message(SessionEvent(ev)))
        self._profile_changed()
        self.set_interval(self.status_interval_s, self.refresh_status)
        self.set_interval(1.0, self._tick)
        self.call_after_refresh(lambda: self.focus_pane(self.panel(TabbedContent).active))
        if self.session.profile is None:
            self.action_pick_profile()

    def panel(self, cls: type[W]) -> W:
        """The one widget of type ``cls`` on the main screen (also while a dialog is open)."""
        return self.screen_stack[0].query_one(cls)

    def on_tabbed_content_tab_activated(self, event: TabbedContent.TabActivated) -> None:
        if event.pane.id == self.panel(TabbedContent).active:  # not a stale activation
            self.focus_pane(event.pane.id)

    def focus_pane(self, tab: str) -> None:
        """Focus the main widget of a tab (the console's input, the log, or the panel)."""
        if not self.main_ready:
            return
        pane = self.screen_stack[0].query_one(f"TabPane#{tab}")
        focus = {"console": "#console-in", "log": "#log-view"}.get(tab)
        candidates = pane.query(focus) if focus else pane.query("*")
        target = next((w for w in candidates if w.focusable), None)
        if target is not None:
            target.focus(scroll_visible=False)

    def action_show_tab(self, tab: str) -> None:
        self.panel(TabbedContent).active = tab
        self.call_after_refresh(self.focus_pane, tab)

    # ---- session events -----------------------------------------------------------------------

    @property
    def main_ready(self) -> bool:
        """False before the main screen is up and after it is gone (shutting down)."""
        return bool(self.screen_stack) and self.screen_stack[0].is_mounted

    def on_session_event(self, message: SessionEvent) -> None:
        if not self.main_ready:
            return
        ev = message.event
        self.tracker.update(ev, time.monotonic())
        self.panel(LogPanel).add_event(ev)
        self.panel(PreviewPanel).handle_session_event(ev)
        self.show_scan()

    def _tick(self) -> None:
        if self.tracker.active and self.main_ready:
            self.show_scan()

    def show_scan(self) -> None:
        now = time.monotonic()
        self.panel(ScanPanel).show_tracker(self.tracker, self.session, now)
        self.panel(Summary).show_scan(self.tracker, self.session, now)

    def _profile_changed(self) -> None:
        p = self.session.profile
        self.sub_title = f"{p.name} — {short_path(p.source)}" if p else "no profile (ctrl+o)"
        self.panel(RigPanel).show_profile(self.session)
        self.show_scan()
        self.refresh_status()

    # ---- device status ------------------------------------------------------------------------

    def refresh_status(self) -> None:
        """Read every device's status in a worker thread (hardware may be slow to answer)."""
        self.run_worker(self._read_status, thread=True, group="status", exclusive=True,
                        exit_on_error=False)

    def _read_status(self) -> None:
        try:
            rows = self.session.devices()
        except Exception as exc:  # a misbehaving backend must not take the UI down
            rows = [{"role": "?", "backend": "?", "connected": False,
                     "status": {"error": f"{type(exc).__name__}: {exc}"}}]
        self.post_message(DeviceRows(rows))

    def on_device_rows(self, message: DeviceRows) -> None:
        if not self.main_ready:
            return
        self.panel(RigPanel).show_rows(message.rows, self.session)
        self.panel(Summary).show_rows(message.rows)

    # ---- actions ------------------------------------------------------------------------------

    def run_session_action(self, label: str, fn: Callable[..., Any], *args: Any,
                   reply_to: Any = None) -> None:
        """Run ``fn(*args)`` (a session call) in a worker thread. Its outcome is posted as
        :class:`ActionDone` to ``reply_to`` (a widget) and errors are logged on the bus."""

        def work() -> None:
            result, error = None, ""
            try:
                result = fn(*args)
            except DotshellError as exc:
                error = str(exc)
            except Exception as exc:  # a bug or a driver failure: show it, keep the UI alive
                error = f"{type(exc).__name__}: {exc}"
                self.session.bus.emit(Message(level="error", text=f"{label} failed:\n"
                                              + traceback.format_exc()))
            else:
                self.refresh_status_later()
            if error:
                self.session.bus.emit(Message(level="error", text=f"{label}: {error}"))
            if reply_to is not None:
                reply_to.post_message(ActionDone(label, result, error))

        self.run_worker(work, thread=True, group=label, exit_on_error=False)

    def refresh_status_later(self) -> None:
        self.call_from_thread(self.refresh_status)

    def start_scan(self, reply_to: Any = None) -> None:
        self.run_session_action("scan", self.session.scan, reply_to=reply_to)

    def load_profile(self, path: str) -> None:
        def done_loading() -> None:
            self.session.load(path)

        self.run_session_action("load profile", done_loading, reply_to=self.panel(RigPanel))

    def on_action_done(self, message: ActionDone) -> None:
        if message.label == "load profile":
            self._profile_changed()

    def action_pick_profile(self) -> None:
        def chosen(path: str | None) -> None:
            if path:
                self.load_profile(path)

        self.push_screen(ProfilePicker(self.session), chosen)

    def action_plugins(self) -> None:
        self.push_screen(PluginsScreen(self.session.pm))

    # ---- quitting -----------------------------------------------------------------------------

    async def action_quit(self) -> None:
        if self._quitting:
            return
        if not self.session.scanning:
            self._close_and_exit()
            return

        def answer(stop: bool | None) -> None:
            if stop:
                self._quitting = True
                self.session.abort()
                self.run_worker(self._wait_and_exit, thread=True, group="quit",
                                exit_on_error=False)

        self.push_screen(ConfirmScreen(
            "A scan is running. Stop it and quit?\nFrames captured so far are kept and the "
            "run is marked aborted.", yes="Stop scan and quit", no="Keep scanning"), answer)

    def on_unmount(self) -> None:
        """However the app ends, a scan it started must not stay paused with nobody to
        resume it: stop it cleanly (frames kept)."""
        self.session.abort()

    def _wait_and_exit(self) -> None:
        for worker in list(self.workers):
            if worker.group == "scan":
                while not worker.is_finished:
                    time.sleep(0.05)
        self.call_from_thread(self._close_and_exit)

    def _close_and_exit(self) -> None:
        if self._unsubscribe is not None:
            self._unsubscribe()
        try:
            self.session.close()
        finally:
            self.exit()


def run_tui(session: Session) -> int:
    """Run the app in the terminal until the user quits."""
    DotshellApp(session).run()
    return 0

