"""The Log panel: the session's events (the scan's and the rig's), filterable by level."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

from rich.text import Text
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.widgets import Label, RichLog, Select

from dotshell.events import Event
from dotshell.tui.text import LEVELS, describe_event

LEVEL_STYLE = {"debug": "dim", "info": "", "warning": "yellow", "error": "bold red"}
MAX_ENTRIES = 20000


@dataclass(frozen=True)
class LogEntry:
    time: float
    level: str
    text: str


class LogPanel(Vertical):
    """Every event as one line; the selector hides lines below a level (``l`` cycles it)."""

    BINDINGS = [Binding("l", "cycle_level", "Level")]

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.entries: list[LogEntry] = []
        self.min_level = "info"

    def compose(self) -> ComposeResult:
        with Horizontal(id="log-bar"):
            yield Label("show from level ")
            yield Select([(lv, lv) for lv in LEVELS], value=self.min_level, allow_blank=False,
                         id="log-level")
        yield RichLog(id="log-view", wrap=True, markup=False, highlight=False, max_lines=5000,
                      min_width=20)

    def visible(self) -> list[LogEntry]:
        floor = LEVELS.index(self.min_level)
        return [e for e in self.entries if LEVELS.index(e.level) >= floor]

    def add_event(self, ev: Event) -> None:
        level, text = describe_event(ev)
        if level not in LEVELS:
            level = "info"
        entry = LogEntry(ev.time, level, text)
        self.entries.append(entry)
        del self.entries[:-MAX_ENTRIES]
        if LEVELS.index(level) >= LEVELS.index(self.min_level):
            self._write(entry)

    def _write(self, e: LogEntry) -> None:
        stamp = time.strftime("%H:%M:%S", time.localtime(e.time))
        line = Text()
        line.append(f"{stamp} {e.level:<7} ", style="dim")
        line.append(e.text, style=LEVEL_STYLE[e.level])
        self.query_one(RichLog).write(line)

    def set_level(self, level: str) -> None:
        self.min_level = level
        select = self.query_one(Select)
        if select.value != level:
            select.value = level
        log = self.query_one(RichLog)
        log.clear()
        for e in self.visible()[-5000:]:
            self._write(e)

    def on_select_changed(self, event: Select.Changed) -> None:
        if isinstance(event.value, str) and event.value != self.min_level:
            self.set_level(event.value)

    def action_cycle_level(self) -> None:
        self.set_level(LEVELS[(LEVELS.index(self.min_level) + 1) % len(LEVELS)])
