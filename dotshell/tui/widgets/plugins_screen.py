"""The plugins screen: every backend of the server's plugin manager by role, name, plugin and
distribution, and the plugins that failed to load — what ``dotshell plugins`` prints."""

from __future__ import annotations

from typing import Any

from rich.markup import escape
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Vertical
from textual.screen import Screen
from textual.widgets import DataTable, Static

from dotshell.tui.widgets.keys_footer import KeysFooter


class PluginsScreen(Screen):
    """Backends and plugin load errors (the server's ``plugins`` reply); escape goes back."""

    BINDINGS = [Binding("escape,q", "app.pop_screen", "Back")]

    def __init__(self, listing: dict[str, Any]) -> None:
        super().__init__()
        self.rows: list[list[str]] = listing["backends"]
        self.errors: list[str] = listing["errors"]

    def compose(self) -> ComposeResult:
        with Vertical(id="plugins"):
            yield Static("[b]Backends[/] (role · name · plugin · distribution · summary)")
            yield DataTable(id="plugins-table", cursor_type="row", zebra_stripes=True)
            yield Static(id="plugins-errors", classes="error")
        yield KeysFooter()

    def on_mount(self) -> None:
        table = self.query_one(DataTable)
        table.add_columns("role", "name", "plugin", "distribution", "summary")
        table.add_rows([tuple(r) for r in self.rows])
        errors = "\n".join(f"failed to load: {escape(e)}" for e in self.errors)
        self.query_one("#plugins-errors", Static).update(errors or "[green]all plugins loaded[/]")
        table.focus()
