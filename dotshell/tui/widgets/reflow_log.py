"""A log that keeps its lines and wraps them for the width it has now: lines written while its
tab is hidden wait (Textual gives a hidden widget no size), and are written when it is shown
again; every new width re-wraps them all — instead of Textual's RichLog wrapping hidden writes
at its minimum width for good."""

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
        self.unwritten = 0  # the last entries not written yet (added while hidden)

    def add(self, line: Text) -> None:
        self.entries.append(line)
        self.unwritten += 1
        self._catch_up(self.size.width)

    def replace(self, lines: Iterable[Text]) -> None:
        self.entries = deque(lines, maxlen=self.entries.maxlen)
        self.laid_out_for = 0
        self._catch_up(self.size.width)

    def on_resize(self, event: Resize) -> None:
        # Textual also runs RichLog.on_resize after this one (it writes what was deferred)
        self._catch_up(event.size.width)

    def _catch_up(self, width: int) -> None:
        """Write the lines added since the last write at ``width`` cells, or wrap them all
        again for a new width. A width of 0 (hidden, or not laid out yet) waits for the resize
        that shows the log."""
        if width <= 0:
            return
        if width != self.laid_out_for or self.unwritten > len(self.entries):
            self._lay_out(width)
            return
        for i in range(len(self.entries) - self.unwritten, len(self.entries)):
            self.write(self.entries[i])
        self.unwritten = 0

    def _lay_out(self, width: int) -> None:
        self.clear()
        self.laid_out_for = width
        self.unwritten = 0
        for line in self.entries:
            self.write(line)
