"""The console's input box: multi-line Python with REPL rules — Enter runs a complete
statement and adds a line to an unfinished one (a blank line ends a block); ↑/↓ on the first
or last line walk the history; ctrl+c interrupts a running input (copies otherwise)."""

from __future__ import annotations

from typing import Any

from textual import events
from textual.message import Message
from textual.widgets import TextArea

from dotshell.tui.interpreter import wants_more


class ConsoleInput(TextArea):
    """A TextArea that submits instead of inserting Enter when the input is complete."""

    class Submitted(Message):
        def __init__(self, source: str) -> None:
            super().__init__()
            self.source = source

    class Interrupt(Message):
        """ctrl+c while an input is running."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(language=None, soft_wrap=True, show_line_numbers=False,
                         tab_behavior="indent", **kwargs)
        self.past_inputs: list[str] = []
        self.past_pos = 0
        self.busy = False
        self._draft = ""

    async def _on_key(self, event: events.Key) -> None:
        handler = {"enter": self._enter, "up": self._history_up, "down": self._history_down,
                   "ctrl+c": self._interrupt}.get(event.key)
        if handler is not None and handler():
            event.stop()
            event.prevent_default()
            return
        await super()._on_key(event)

    def _enter(self) -> bool:
        row, _ = self.cursor_location
        single_line = "\n" not in self.text
        at_end = row == self.document.line_count - 1
        if (single_line or at_end) and not wants_more(self.text):
            self.submit()
            return True
        line = self.document.get_line(row)
        indent = line[: len(line) - len(line.lstrip())]
        if line.rstrip().endswith(":"):
            indent += "    "
        self.insert("\n" + indent)
        return True

    def submit(self) -> None:
        source = self.text.rstrip()
        if not source.strip():
            return
        if not self.past_inputs or self.past_inputs[-1] != source:
            self.past_inputs.append(source)
        self.past_pos = len(self.past_inputs)
        self.text = ""
        self.post_message(self.Submitted(source))

    def _history_up(self) -> bool:
        if self.cursor_location[0] != 0 or not self.past_inputs or self.past_pos == 0:
            return False
        if self.past_pos == len(self.past_inputs):
            self._draft = self.text
        self.past_pos -= 1
        self._show(self.past_inputs[self.past_pos])
        return True

    def _history_down(self) -> bool:
        if (self.cursor_location[0] != self.document.line_count - 1
                or self.past_pos >= len(self.past_inputs)):
            return False
        self.past_pos += 1
        self._show(self.past_inputs[self.past_pos] if self.past_pos < len(self.past_inputs)
                   else self._draft)
        return True

    def _show(self, text: str) -> None:
        self.text = text
        self.move_cursor(self.document.end)

    def _interrupt(self) -> bool:
        if not self.busy:
            return False  # TextArea copies the selection
        self.post_message(self.Interrupt())
        return True
