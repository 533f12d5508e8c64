"""The keys overlay (``?`` or F1): every key of the app, where it works and what it does,
read from the bindings themselves so it cannot go stale; it scrolls with the arrows and page
keys from the start; escape, ``?`` or F1 close it."""

from __future__ import annotations

from typing import Iterable

from rich.table import Table
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import VerticalScroll
from textual.screen import ModalScreen
from textual.widgets import Static

#: Keys handled inside the console's input box (not bindings).
CONSOLE_KEYS = [("enter", "run a complete input (adds a line to an open block)"),
                ("↑ ↓", "history, on the first / last line"),
                ("tab", "complete the name before the cursor"),
                ("pgup pgdn", "scroll the output"),
                ("^c", ("interrupt the running input (a scan is aborted cleanly); copy the "
                        "selection in the box when nothing runs")),
                ("^y", "copy the last input's output to the clipboard (OSC 52)"),
                ("esc", "stop motion, as on every tab"),
                ("^d", "end of file for a waiting input()")]


class KeysScreen(ModalScreen[None]):
    """A table of (where, key, what) rows."""

    BINDINGS = [Binding("escape,question_mark,f1,q", "close", "Close")]

    def __init__(self, sections: Iterable[tuple[str, list[tuple[str, str]]]]) -> None:
        super().__init__()
        self.sections = list(sections)

    def compose(self) -> ComposeResult:
        table = Table(box=None, expand=True, pad_edge=False, header_style="bold")
        table.add_column("where", no_wrap=True, style="dim")
        table.add_column("key", no_wrap=True, style="bold")
        table.add_column("what", ratio=1)
        for where, keys in self.sections:
            for i, (key, what) in enumerate(keys):
                table.add_row(where if i == 0 else "", key, what)
        with VerticalScroll(classes="dialog", id="keys"):
            yield Static("[b]Keys[/] — escape closes; ^p searches every command",
                         classes="question")
            yield Static(table)

    def on_mount(self) -> None:
        """The table scrolls at once (↑ ↓ pgup pgdn home end): it holds the focus."""
        self.query_one("#keys", VerticalScroll).focus()

    def action_close(self) -> None:
        self.dismiss(None)
