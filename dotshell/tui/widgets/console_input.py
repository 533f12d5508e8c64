"""The console's input box: multi-line Python with REPL rules — Enter runs a complete
statement and adds a line to an unfinished one (a blank line ends a block); ↑/↓ on the first
or last line walk the history; Tab completes the name before the cursor (indents elsewhere);
ctrl+c interrupts a running input (copies otherwise); page up/down scroll the output. While
the running input waits in ``input()`` (or ``help()``), Enter sends the line to it and ctrl+d
ends its input."""

from __future__ import annotations

import os
import re
from typing import Any

from textual import events
from textual.message import Message
from textual.widgets import TextArea

from dotshell.server.interpreter import wants_more

_TOKEN_END = re.compile(r"[A-Za-z_][\w.]*$")
#: An Enter this soon after the key before it (seconds) is part of a paste arriving as keys
#: (a terminal without bracketed paste sends them in one burst, microseconds apart; typing
#: is tens of milliseconds apart, Textual's Pilot too).
PASTE_GAP_S = 0.01


class ConsoleInput(TextArea):
    """A TextArea that submits instead of inserting Enter when the input is complete."""

    class Submitted(Message):
        def __init__(self, source: str) -> None:
            super().__init__()
            self.source = source

    class Reply(Message):
        """A line for the running input's ``input()`` (None: end of file)."""

        def __init__(self, line: str | None) -> None:
            super().__init__()
            self.line = line

    class Interrupt(Message):
        """ctrl+c while an input is running."""

    class Page(Message):
        """page up / page down: scroll the console's output."""

        def __init__(self, up: bool) -> None:
            super().__init__()
            self.up = up

    class CopyOutput(Message):
        """ctrl+y: copy the output of the last input."""

    class CompleteRequest(Message):
        def __init__(self, text: str) -> None:
            super().__init__()
            self.text = text

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(language=None, soft_wrap=True, show_line_numbers=False,
                         tab_behavior="indent", **kwargs)
        self.past_inputs: list[str] = []
        self.past_pos = 0
        self.busy = False
        self.waiting_prompt: str | None = None
        self._draft = ""
        self._last_key_s = 0.0  # when the last key came (monotonic seconds)

    async def _on_key(self, event: events.Key) -> None:
        gap_s, self._last_key_s = event.time - self._last_key_s, event.time
        if event.key == "enter" and gap_s < PASTE_GAP_S and self.waiting_prompt is None:
            # a paste without bracketed paste (keys in one burst): its newlines are text — no
            # auto-indent on top of the pasted indentation, no run in the middle of it
            self.insert("\n")
            event.stop()
            event.prevent_default()
            return
        handler = {"enter": self._enter, "up": self._history_up, "down": self._history_down,
                   "ctrl+c": self._interrupt, "ctrl+d": self._end_of_file,
                   "tab": self._complete, "ctrl+y": self._copy_output, "pageup": lambda: self._page(True),
                   "pagedown": lambda: self._page(False)}.get(event.key)
        if handler is not None and handler():
            event.stop()
            event.prevent_default()
            return
        if event.key == "escape":  # the app's stop key, as on every tab: TextArea would move
            event.prevent_default()  # the focus away; the event goes on to the app
            return
        await super()._on_key(event)

    def _enter(self) -> bool:
        if self.waiting_prompt is not None:
            line, self.text = self.text, ""
            self.post_message(self.Reply(line))
            return True
        if not self.text.strip():
            self.text = ""  # an empty Enter adds nothing (it added an invisible newline)
            return True
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

    def set_history(self, inputs: list[str]) -> None:
        self.past_inputs = list(inputs)
        self.past_pos = len(self.past_inputs)

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

    def _copy_output(self) -> bool:
        self.post_message(self.CopyOutput())
        return True

    def _page(self, up: bool) -> bool:
        self.post_message(self.Page(up))
        return True

    def _end_of_file(self) -> bool:
        if self.waiting_prompt is None or self.text:
            return False
        self.post_message(self.Reply(None))
        return True

    # ---- completion ---------------------------------------------------------------------------

    def before_cursor(self) -> str:
        return self.document.get_text_range((0, 0), self.cursor_location)

    def _complete(self) -> bool:
        if self.waiting_prompt is not None or not _TOKEN_END.search(self.before_cursor()):
            return False  # Tab indents
        self.post_message(self.CompleteRequest(self.before_cursor()))
        return True

    def apply_completion(self, token: str, matches: list[str]) -> None:
        """Replace the ``token`` before the cursor with the only match, or extend it to what
        all matches share."""
        if not matches or not self.before_cursor().endswith(token):
            return
        common = matches[0] if len(matches) == 1 else os.path.commonprefix(matches)  # noqa: RUF071 (text, not paths)
        if len(common) > len(token):
            row, col = self.cursor_location
            self.replace(common, (row, col - len(token)), (row, col))
