"""``dotshell tui``: the Textual app, a front end of a rig server. It holds a
:class:`~dotshell.server.client.RemoteSession` — no devices, no frames — forwards what the
server pushes (events, state, device status, console output) to the panels as messages, and
runs every request in a worker thread so the UI never waits on hardware. Quitting during a scan
offers to leave it running on the server; a terminal that goes away just ends this process.

Layout: a header (profile, server, who controls), a tabbed body (1 Rig, 2 Scan, 3 Preview,
4 Log, 5 Console), the footer with the keys; from 100 columns on a summary sidebar shows the
server, the rig and the scan next to any tab.
"""

from __future__ import annotations

import os
import re
import threading
import time
import traceback
from collections import deque
from typing import Any, Callable, Iterable, TypeVar

from textual.app import App, ComposeResult, SystemCommand
from textual.binding import Binding
from textual.containers import Horizontal
from textual.screen import Screen
from textual.widget import Widget
from textual.widgets import ContentSwitcher, Header, TabbedContent, TabPane
from textual.widgets._tabbed_content import ContentTabs

from dotshell.errors import DotshellError
from dotshell.server.client import RemoteSession
from dotshell.runtime.paths import user_config
from dotshell.server.progress import ScanTracker
from dotshell.server.protocol import event_from_wire
from dotshell.tui.messages import ActionDone, ServerBatch, ServerMessage
from dotshell.tui.redraw import DrawnWhileShown
from dotshell.tui.themes import FEW_COLOURS, FEW_COLOURS_THEME, few_colours_theme, no_color_ansi
from dotshell.tui.widgets.console_input import ConsoleInput
from dotshell.tui.widgets.console_panel import ConsolePanel
from dotshell.tui.widgets.keys_footer import KeysFooter
from dotshell.tui.widgets.keys_screen import CONSOLE_KEYS, KeysScreen
from dotshell.tui.widgets.log_panel import LogPanel
from dotshell.tui.widgets.plugins_screen import PluginsScreen
from dotshell.tui.widgets.preview_panel import PreviewPanel
from dotshell.tui.widgets.profile_picker import ProfilePicker
from dotshell.tui.widgets.quit_screen import QuitScreen
from dotshell.tui.widgets.rig_panel import RigPanel
from dotshell.tui.widgets.scan_panel import ScanPanel
from dotshell.tui.widgets.summary import Summary

W = TypeVar("W", bound=Widget)
TABS = ("rig", "scan", "preview", "log", "console")
#: The widget that takes the focus when a tab is shown (None: the pane's first focusable one).
TAB_FOCUS = {"console": "#console-in", "log": "#log-view"}
#: Previews replayed from the server's backlog when attaching.
REPLAYED_PREVIEWS = 5
#: Server messages handled at most in one go (keys pressed meanwhile come between batches).
BATCH_MAX = 200


class DotshellApp(App):
    """The instrument shell's terminal UI over one rig server's session."""

    TITLE = "dotshell"
    CSS_PATH = "app.tcss"
    AUTO_FOCUS = "#rig-panel"  # the first tab's panel: its keys work at once
    HORIZONTAL_BREAKPOINTS = [(0, "-narrow"), (100, "-wide")]
    BINDINGS = [
        Binding("ctrl+q", "quit", "Quit", priority=True),
        Binding("question_mark,f1", "keys", "Keys", key_display="?"),
        Binding("escape", "stop", "Stop", key_display="esc"),
        Binding("p", "pause", "Pause/resume", show=False),
        Binding("x", "abort", "Abort", show=False),
        Binding("ctrl+o", "pick_profile", "Profile"),
        Binding("ctrl+g", "plugins", "Plugins", show=False),
        Binding("ctrl+t", "take_control", "Take control", show=False),
        *(Binding(f"{i + 1},f{i + 2}", f"show_tab('{tab}')", tab.title(), show=False)
          for i, tab in enumerate(TABS)),
    ]

    def __init__(self, session: RemoteSession, notice: str = "") -> None:
        super().__init__(ansi_color=no_color_ansi())
        if "TEXTUAL_ANIMATIONS" not in os.environ:
            # No animations unless asked for: the tab bar's sliding underline alone redraws
            # the screen some 15 times a tab switch — over SSH each is a screen update sent.
            self.animation_level = "none"
        self.session = session
        self.notice = notice
        self.tracker = ScanTracker.from_dict(session.tracker.to_dict())
        self._unsubscribe: Callable[[], None] | None = None
        self._quitting = False
        self._main_up = False
        self._inbox: deque[dict[str, Any]] = deque()
        self._inbox_lock = threading.Lock()
        self._batch_queued = False
        self._scan_changed = False
        self._batching = False

    # ---- layout -------------------------------------------------------------------------------

    def compose(self) -> ComposeResult:
        yield Header(show_clock=False)
        with Horizontal(id="body"):
            yield Summary(id="summary")
            with TabbedContent(id="tabs", initial="rig"):
                with TabPane("1 Rig", id="rig"):
                    yield RigPanel(id="rig-panel")
                with TabPane("2 Scan", id="scan"):
                    yield ScanPanel(id="scan-panel")
                with TabPane("3 Preview", id="preview"):
                    yield PreviewPanel(id="preview-panel")
                with TabPane("4 Log", id="log"):
                    yield LogPanel(id="log-panel")
                with TabPane("5 Console", id="console"):
                    yield ConsolePanel(id="console-panel")
        yield KeysFooter()

    def on_mount(self) -> None:
        self._main_up = True
        switcher = self.panel(TabbedContent).query_one(ContentSwitcher)
        self.watch(switcher, "current", self._pane_switched_to, init=False)
        log = self.panel(LogPanel)
        previews = []
        for ev in self.session.backlog:
            log.add_event(ev)
            if hasattr(ev, "kind") and hasattr(ev, "path"):
                previews.append(ev)
        for ev in previews[-REPLAYED_PREVIEWS:]:
            self.panel(PreviewPanel).handle_session_event(ev)
        self.panel(ConsoleInput).set_history(self.session.history)
        self.panel(ConsolePanel).replay(self.session.console_transcript,
                                        self.session.state.get("console") or {})
        self._unsubscribe = self.session.subscribe(self._from_server)
        if self.notice:
            log.add("info", self.notice)
            self.notify(self.notice, timeout=8,
                        severity="warning" if "NOT applied" in self.notice else "information")
        if self.console.color_system in FEW_COLOURS:  # else headings read red like errors
            self.register_theme(few_colours_theme())
            self.theme = FEW_COLOURS_THEME
        if self.console.color_system != "truecolor":
            log.add("warning", f"this terminal shows {self.console.color_system or 'no'} colours: "
                    "previews are approximate (a truecolor terminal, COLORTERM=truecolor, shows "
                    "them as they are)")
        self._state_changed()
        self.panel(RigPanel).show_rows(self.session.rows)
        self.panel(Summary).show_rows(self.session.rows)
        self.set_interval(1.0, self._tick)
        if self.session.profile is None and not self.session.scanning:
            self.action_pick_profile()

    def panel(self, cls: type[W]) -> W:
        """The one widget of type ``cls`` on the main screen (also while a dialog is open)."""
        return self.screen_stack[0].query_one(cls)

    @property
    def main_ready(self) -> bool:
        """False before the main screen's panels are up (:meth:`on_mount` has not run) and
        from the moment the app shuts down (Textual stops the app, then removes the screens'
        widgets: a server message still queued then found no panel to show it in). True
        while Textual is still mounting the main screen after :meth:`on_mount`: the panels
        are there and take what they show (as in :meth:`on_mount`); the server's messages of
        that moment were dropped before, the device list among them (an empty table until
        the next change, seen in a real terminal on a loaded machine)."""
        return self._main_up and self.is_running and bool(self.screen_stack)

    # ---- tabs and focus -----------------------------------------------------------------------

    def _focus_target(self, tab: str) -> Widget | None:
        pane = self.screen_stack[0].query_one(f"TabPane#{tab}")
        selector = TAB_FOCUS.get(tab)
        candidates = pane.query(selector) if selector else pane.query("*")
        return next((w for w in candidates if w.focusable), None)

    def action_show_tab(self, tab: str) -> None:
        """Show a tab by focusing its main widget first: TabbedContent then shows the pane that
        holds the focus. (Switching the pane first hides the focused widget, Textual hands the
        focus to a hidden sibling — the console's log — and switches back: the F-key bounce.)"""
        if not self.main_ready:
            return
        target = self._focus_target(tab)
        if target is not None:
            target.focus(scroll_visible=False)  # takes effect before the switch below
        self.call_later(setattr, self.panel(TabbedContent), "active", tab)

    def _pane_switched_to(self, pane_id: str | None) -> None:
        """The panels of the pane just shown draw what they missed while hidden: at once,
        before the screen is laid out and painted with the pane, so no frame is stale."""
        if not (pane_id and self.main_ready):
            return
        self.screen_stack[0].set_class(pane_id == "console", "-console-shown")
        for widget in self.screen_stack[0].query_one(f"TabPane#{pane_id}").walk_children():
            if isinstance(widget, DrawnWhileShown):
                widget.catch_up()

    def on_tabbed_content_tab_activated(self, event: TabbedContent.TabActivated) -> None:
        """A tab chosen on the tab bar: the bar keeps the focus while the user walks along it
        with the arrows; otherwise (a click elsewhere) the pane's widget takes it."""
        if event.pane.id != self.panel(TabbedContent).active:
            return  # a stale activation
        focused = self.focused
        if isinstance(focused, ContentTabs):
            return
        if focused is None or event.pane not in focused.ancestors_with_self:
            target = self._focus_target(event.pane.id or "")
            if target is not None:
                target.focus(scroll_visible=False)

    # ---- what the server says -----------------------------------------------------------------

    def _from_server(self, message: dict[str, Any]) -> None:
        """On the client's reader thread: keep the message, and queue one batch for the UI
        thread unless one is queued already."""
        with self._inbox_lock:
            self._inbox.append(message)
            if self._batch_queued:
                return
            self._batch_queued = True
        self.post_message(ServerBatch())

    def on_server_batch(self, _: ServerBatch) -> None:
        """Handle the waiting server messages (at most :data:`BATCH_MAX`; the rest after any
        key pressed meanwhile), and redraw the scan's progress once for all of them."""
        with self._inbox_lock:
            batch = [self._inbox.popleft() for _ in range(min(len(self._inbox), BATCH_MAX))]
            more = self._batch_queued = bool(self._inbox)
        self._batching = True
        try:
            for m in batch:
                self.on_server_message(ServerMessage(m))
        finally:
            self._batching = False
        if self._scan_changed and self.main_ready:
            self._scan_changed = False
            self.show_scan()
        if more:
            self.post_message(ServerBatch())

    def on_server_message(self, message: ServerMessage) -> None:
        if not self.main_ready:
            return
        m = message.message
        kind = m.get("type")
        if kind == "event":
            ev = event_from_wire(m["event"])
            self.tracker.update(ev)
            self.panel(LogPanel).add_event(ev)
            self.panel(PreviewPanel).handle_session_event(ev)
            self.show_scan()
        elif kind == "state":
            self._state_changed()
        elif kind == "devices":
            self.panel(RigPanel).show_rows(m["rows"])
            self.panel(Summary).show_rows(m["rows"])
        elif kind in ("console", "console_input", "console_done"):
            self.panel(ConsolePanel).handle(m)
        elif kind == "control":
            self.panel(LogPanel).add("warning", m.get("text", "control moved"))
            self.notify(f"{m.get('text', 'control moved')}: you are watching now (ctrl+t "
                        "takes it back)", severity="warning", timeout=10)
        elif kind == "closed" and not self._quitting:
            self._quitting = True
            self.exit(return_code=1, message=f"dotshell tui: {m.get('reason', 'disconnected')}")

    def _state_changed(self) -> None:
        s = self.session
        p = s.profile
        c = s.controller
        control = ("in control" if s.in_control else
                   f"watching: {c['client']}#{c['id']} controls (^t takes over)" if c else
                   "watching: nobody controls (^t)")
        self.sub_title = f"{p['name'] if p else 'no profile (^o)'} · {control}"
        self.panel(RigPanel).show_profile()
        self.panel(Summary).show_server(s)
        self.show_scan()

    def _tick(self) -> None:
        if self.tracker.active and self.main_ready:
            self.show_scan()

    def show_scan(self) -> None:
        if self._batching:  # drawn once when the batch is done
            self._scan_changed = True
            return
        now = time.time()
        self.panel(ScanPanel).show_tracker(self.tracker, now)
        self.panel(Summary).show_scan(self.tracker, self.session, now)

    # ---- requests -----------------------------------------------------------------------------

    def run_session_action(self, label: str, fn: Callable[..., Any], *args: Any,
                           reply_to: Any = None, then: Callable[[Any], object] | None = None) -> None:
        """Run ``fn(*args)`` (a request to the server) in a worker thread. Its outcome is posted
        as :class:`ActionDone` to ``reply_to`` (a widget); ``then(result)`` runs on the UI thread
        after a success; errors are logged."""

        def work() -> None:
            result, error = None, ""
            try:
                result = fn(*args)
            except DotshellError as exc:
                error = str(exc)
            except Exception as exc:  # a bug or a lost server: show it, keep the UI alive
                error = f"{type(exc).__name__}: {exc}"
                self.call_from_thread(self.log_line, "error",
                                      f"{label} failed:\n{traceback.format_exc()}")
            if error:
                self.call_from_thread(self.log_line, "error", f"{label}: {error}")
            elif then is not None:
                self.call_from_thread(then, result)
            if reply_to is not None:
                reply_to.post_message(ActionDone(label, result, error))

        self.run_worker(work, thread=True, group=label, exit_on_error=False)

    def log_line(self, level: str, text: str) -> None:
        """A line of this front end's own (the server does not see it) in the Log tab."""
        if self.main_ready:
            self.panel(LogPanel).add(level, text)

    def action_stop(self) -> None:
        """The stop key (any client, any tab): stop motion, never abort. Pending jogs are
        dropped; during a scan the scan pauses before its next frame (``p`` resumes, ``x``
        aborts), otherwise every device that can move stops now."""
        self.panel(RigPanel).stop()

    def check_action(self, action: str, parameters: tuple[object, ...]) -> bool | None:
        """``p`` and ``x`` act on the main screen only: not under a dialog, where the app's
        keys would otherwise still reach them (x in a confirmation asked again)."""
        if action in ("pause", "abort") and len(self.screen_stack) > 1:
            return False
        return super().check_action(action, parameters)

    def action_pause(self) -> None:
        """``p`` on any tab but the Console: pause the scan, or resume a paused one."""
        self.panel(ScanPanel).action_pause()

    def action_abort(self) -> None:
        """``x`` on any tab but the Console: abort the scan after a yes."""
        self.panel(ScanPanel).action_abort()

    def action_take_control(self) -> None:
        self.run_session_action("take control", self.session.take_control)

    def load_profile(self, path: str) -> None:
        self.run_session_action("load profile", self.session.load, path,
                                reply_to=self.panel(RigPanel))

    def action_pick_profile(self) -> None:
        def chosen(path: str | None) -> None:
            if path:
                self.load_profile(path)

        try:
            extra = user_config()["profile_dirs"]
        except DotshellError as exc:
            self.log_line("warning", str(exc))
            extra = []
        p = self.session.profile
        self.push_screen(ProfilePicker(p["path"] if p else None, extra), chosen)

    def action_plugins(self) -> None:
        self.run_session_action("plugins", self.session.plugins,
                                then=lambda listing: self.push_screen(PluginsScreen(listing)))

    def action_keys(self) -> None:
        if not isinstance(self.screen, KeysScreen):
            self.push_screen(KeysScreen(self.key_sections()))

    def key_sections(self) -> list[tuple[str, list[tuple[str, str]]]]:
        """(where, [(keys, what)]) for the keys overlay, from the bindings themselves."""

        def rows(bindings: Iterable[Binding | tuple]) -> list[tuple[str, str]]:
            out = []
            for b in bindings:  # a panel's app.* bindings only show the app's in its footer
                if isinstance(b, Binding) and not b.action.startswith("app."):
                    keys = " ".join(re.sub(r"^f(\d+)$", r"F\1", self.get_key_display(
                        Binding(k, b.action, key_display=b.key_display if "," not in b.key
                                else None))) for k in b.key.split(","))
                    out.append((keys, b.description or b.action))
            return out

        return [("anywhere", rows(self.BINDINGS) + [("^p", "search every command")]),
                ("Rig", rows(RigPanel.BINDINGS)), ("Scan", rows(ScanPanel.BINDINGS)),
                ("Preview", rows(PreviewPanel.BINDINGS)), ("Log", rows(LogPanel.BINDINGS)),
                ("Console", CONSOLE_KEYS)]

    def get_system_commands(self, screen: Screen) -> Iterable[SystemCommand]:
        """dotshell's own actions in the command palette (ctrl+p), before Textual's."""
        rig, scan = self.panel(RigPanel), self.panel(ScanPanel)
        commands: list[tuple[str, str, Callable[[], Any]]] = [
            ("Connect the rig", "connect every device", rig.action_connect),
            ("Disconnect the rig", "close every device", rig.action_disconnect),
            ("Start scan", "scan with the loaded profile (Scan: s)", scan.action_start),
            ("Pause or resume the scan", "between frames (Scan: p)", scan.action_pause),
            ("Stop motion", ("pause a scan before its next frame, else stop every moving "
                             "device; never aborts (esc)"), self.action_stop),
            ("Go to stage angle", "absolute, degrees (Rig: g)", rig.action_goto),
            ("Home the stage", "find its reference position (Rig: h)", rig.action_home),
            ("Jog stage +", "by the jog step (Rig: ])", lambda: rig.action_jog(1)),
            ("Jog stage −", "by the jog step (Rig: [)", lambda: rig.action_jog(-1)),
            ("Set analyzer angle", "degrees (Rig: a)", rig.action_analyzer),
            ("Set camera exposure", "ms (Rig: e)", rig.action_exposure),
            ("Snap a frame", "with the current pattern (Rig: space)", rig.action_snap),
            ("Project a pattern", "from the coding's sequence (Rig: t)", rig.action_project),
            ("Decode map", "project, capture and decode here (Rig: m)", rig.action_decode),
            ("Load profile", "pick a profile (ctrl+o)", self.action_pick_profile),
            ("Plugins", "backends and load errors (ctrl+g)", self.action_plugins),
            ("Take control", "of the rig from another front end (ctrl+t)",
             self.action_take_control),
            ("Detach", "quit this terminal, leave the server and its scan running",
             self.detach_and_exit),
            *((f"Show {tab.title()}", f"tab {i + 1}", lambda tab=tab: self.action_show_tab(tab))
              for i, tab in enumerate(TABS)),
        ]
        for title, help_text, callback in commands:
            yield SystemCommand(title, help_text, callback)
        # found only when searched for, never the entry Enter picks in an empty palette, and
        # it asks first like x
        yield SystemCommand("Abort the scan", "asks first; frames are kept, run aborted "
                            "(Scan: x)", scan.action_abort, discover=False)
        yield from super().get_system_commands(screen)

    # ---- quitting -----------------------------------------------------------------------------

    async def action_quit(self) -> None:
        if self._quitting:
            return
        if not (self.session.scanning and self.session.in_control):
            self.detach_and_exit()
            return

        def answer(choice: str | None) -> None:
            if choice == "leave":
                self.detach_and_exit()
            elif choice == "stop":
                self.run_session_action("abort", self.session.abort,
                                        then=lambda _: self.detach_and_exit())

        self.push_screen(QuitScreen(
            "A scan is running on the rig server. Leave it running (it goes on without this "
            "terminal; dotshell tui or dotshell attach shows it again), or stop it and quit "
            "(frames captured so far are kept and the run is marked aborted)?"), answer)

    def detach_and_exit(self) -> None:
        """Leave: the server (and a scan) go on; an idle server a front end started exits
        by itself once nobody is attached."""
        self._quitting = True
        self.exit()

    def on_unmount(self) -> None:
        if self._unsubscribe is not None:
            self._unsubscribe()
        self.session.close()


def run_tui(session: RemoteSession, notice: str = "") -> int:
    """Run the app in the terminal until the user quits or the server goes away."""
    app = DotshellApp(session, notice)
    app.run()
    return app.return_code or 0
