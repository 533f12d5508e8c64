"""The plugins screen: every backend by role, name, plugin and distribution, and the plugins
that failed to load — what ``dotshell plugins`` prints."""

from __future__ import annotations

from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Vertical
from textual.screen import Screen
from textual.widgets import DataTable, Footer, Static

from dotshell.backends import ROLES
from dotshell.plugins import PluginManager


def backend_rows(pm: PluginManager) -> list[tuple[str, str, str, str, str]]:
    """(role, name, plugin, distribution, summary) of every backend, by role then name."""
    return [(role, name, info.plugin, info.distribution, info.backend.summary)
            for role in ROLES for name, info in sorted(pm.backends(role).items())]


class PluginsScreen(Screen):
    """Backends and plugin load errors; escape goes back."""

    BINDINGS = [Binding("escape,q", "app.pop_screen", "Back")]

    def __init__(self, pm: PluginManager) -> None:
        super().__init__()
        self.pm = pm

    def compose(self) -> ComposeResult:
        with Vertical(id="plugins"):
            yield Static("[b]Backends[/] (role · name · plugin · distribution · summary)")
            yield DataTable(id="plugins-table", cursor_type="row", zebra_stripes=True)
            yield Static(id="plugins-errors", classes="error")
        yield Footer()

    def on_mount(self) -> None:
        table = self.query_one(DataTable)
        table.add_columns("role", "name", "plugin", "distribution", "summary")
        table.add_rows(backend_rows(self.pm))
        errors = "\n".join(f"failed to load: {e}" for e in self.pm.load_errors)
        self.query_one("#plugins-errors", Static).update(errors or "[green]all plugins loaded[/]")
        table.focus()
