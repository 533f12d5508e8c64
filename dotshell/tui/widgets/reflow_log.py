"""A log that keeps its lines and wraps them for the width it has now: lines written while its
tab is hidden (no width) wait, and every new width re-wraps them all — instead of Textual's
RichLog wrapping hidden writes at its minimum width for good."""

from __future__ import annotations

from collections import deque
from typing import Any, Iterable

from rich.text import Text
from textual.events import Resize
from textual.widgets import RichLog


class ReflowLog(RichLog):
    """``add(text)`` appends a line; ``replace(lines)`` sets them all."""

    def __init__(self, max_entries: int = 5000, **kwargs: Any) -> None:
        super().__init__(wrap=True, markup=False, highlight=False, max_lines=max_entries,
                         min_width=1, **kwargs)
        self.entries: deque[Text] = deque(maxlen=max_entries)
        self.laid_out_for = 0  # the widget width the shown lines were wrapped for

    def add(self, line: Text) -> None:
        self.entries.append(line)
        width = self.size.width
        if width > 0 and width == self.laid_out_for:
            self.write(line)
        elif width > 0:
            self._lay_out(width)

    def replace(self, lines: Iterable[Text]) -> None:
        self.entries = deque(lines, maxlen=self.entries.maxlen)
        self.laid_out_for = 0
        if self.size.width > 0:
            self._lay_out(self.size.width)

    def on_resize(self, event: Resize) -> None:
        # Textual also runs RichLog.on_resize after this one (it writes what was deferred)
        if event.size.width > 0 and event.size.width != self.laid_out_for:
            self._lay_out(event.size.width)

    def _lay_out(self, width: int) -> None:
        self.clear()
        self.laid_out_for = width
        for line in self.entries:
            self.write(line)
