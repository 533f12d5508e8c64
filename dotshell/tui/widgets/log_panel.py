"""The Log panel: the session's events (the scan's, every rig action, the server's notes),
filterable by level. Lines keep their wrapping right however the tab was hidden or resized."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

from rich.text import Text
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.widgets import Label, Select

from dotshell.events import Event
from dotshell.server.describe import LEVELS, describe_event
from dotshell.tui.text import copy_text
from dotshell.tui.widgets.reflow_log import ReflowLog

LEVEL_STYLE = {"debug": "dim", "info": "", "warning": "yellow", "error": "bold red"}
MAX_ENTRIES = 20000
SHOWN = 5000


@dataclass(frozen=True)
class LogEntry:
    time: float
    level: str
    text: str


class LogPanel(Vertical):
    """Every event as one line; the selector hides lines below a level (``l`` cycles it)."""

    BINDINGS = [Binding("l", "cycle_level", "Level"),
                Binding("y", "copy(False)", "Copy line", show=False),
                Binding("Y", "copy(True)", "Copy all", show=False)]

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.entries: list[LogEntry] = []
        self.min_level = "info"

    def compose(self) -> ComposeResult:
        with Horizontal(id="log-bar"):
            yield Label("show from level ")
            yield Select([(lv, lv) for lv in LEVELS], value=self.min_level, allow_blank=False,
                         id="log-level")
        yield ReflowLog(max_entries=SHOWN, id="log-view")

    def visible_entries(self) -> list[LogEntry]:
        floor = LEVELS.index(self.min_level)
        return [e for e in self.entries if LEVELS.index(e.level) >= floor]

    def add_event(self, ev: Event) -> None:
        level, text = describe_event(ev)
        self.add(level, text, ev.time)

    def add(self, level: str, text: str, when: float | None = None) -> None:
        """One line (also for the front end's own notes, which the server does not see)."""
        if level not in LEVELS:
            level = "info"
        entry = LogEntry(when or time.time(), level, text)
        self.entries.append(entry)
        del self.entries[:-MAX_ENTRIES]
        if LEVELS.index(level) >= LEVELS.index(self.min_level):
            self.query_one(ReflowLog).add(self._line(entry))

    @staticmethod
    def plain(e: LogEntry) -> str:
        """A line as copied: ``HH:MM:SS level   text``."""
        stamp = time.strftime("%H:%M:%S", time.localtime(e.time))
        return f"{stamp} {e.level:<7} {e.text}"

    def action_copy(self, everything: bool) -> None:
        """``y``: the newest line shown, ``Y``: every line shown (at the chosen level), to the
        clipboard — the terminal's (OSC 52) where it allows it."""
        shown = self.visible_entries()[-SHOWN:]
        if not shown:
            self.app.notify("nothing to copy: no line is shown", severity="warning")
            return
        lines = shown if everything else shown[-1:]
        copy_text(self.app, "\n".join(self.plain(e) for e in lines) + "\n",
                  f"{len(lines)} log line{'s' if len(lines) > 1 else ''}")

    @staticmethod
    def _line(e: LogEntry) -> Text:
        stamp = time.strftime("%H:%M:%S", time.localtime(e.time))
        line = Text()
        line.append(f"{stamp} {e.level:<7} ", style="dim")
        line.append(e.text, style=LEVEL_STYLE[e.level])
        return line

    def set_level(self, level: str) -> None:
        self.min_level = level
        select = self.query_one(Select)
        if select.value != level:
            select.value = level
        self.query_one(ReflowLog).replace(self._line(e) for e in self.visible_entries()[-SHOWN:])

    def on_select_changed(self, event: Select.Changed) -> None:
        if isinstance(event.value, str) and event.value != self.min_level:
            self.set_level(event.value)

    def action_cycle_level(self) -> None:
        self.set_level(LEVELS[(LEVELS.index(self.min_level) + 1) % len(LEVELS)])
