"""The sidebar shown from 100 columns on: the server, the rig's devices and the scan at a
glance."""

from __future__ import annotations

import time
from typing import Any

from rich.markup import escape
from textual.app import ComposeResult
from textual.containers import Vertical
from textual.widgets import Static

from dotshell.server.progress import ScanTracker
from dotshell.tui.redraw import DrawnWhileShown, show
from dotshell.tui.text import describe_status


class Summary(DrawnWhileShown, Vertical):
    """Compact server, device and scan status, redrawn by the app (while the sidebar is shown:
    from the latest state when a wider terminal shows it again)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.rows: list[dict[str, Any]] = []

    def compose(self) -> ComposeResult:
        yield Static("[b]Server[/]", classes="summary-title")
        yield Static(id="summary-server")
        yield Static("[b]Rig[/]", classes="summary-title")
        yield Static(id="summary-rig")
        yield Static("[b]Scan[/]", classes="summary-title")
        yield Static(id="summary-scan")

    def redraw(self) -> None:
        session = self.app.session  # type: ignore[attr-defined]
        self.show_server(session)
        self.show_rows(self.rows)
        self.show_scan(self.app.tracker, session, time.time())  # type: ignore[attr-defined]

    def show_server(self, session: Any) -> None:
        if not self.drawing():
            return
        state = session.state
        c = state.get("controller")
        who = ("you control" if session.in_control else
               f"{c['client']}#{c['id']} controls" if c else "nobody controls")
        show(self.query_one("#summary-server", Static),
             f"{escape(session.server_name)}\n{who}; {len(state.get('clients', []))} attached")

    def show_rows(self, rows: list[dict[str, Any]]) -> None:
        self.rows = rows
        if not self.drawing():
            return
        lines = []
        for row in rows:
            mark = "[green]●[/]" if row["connected"] else "[dim]○[/]"
            status = describe_status(row["role"], row["status"], compact=True)
            lines.append(f"{mark} {row['role']}" + (f"\n   {escape(status)}" if status else ""))
        show(self.query_one("#summary-rig", Static), "\n".join(lines) or "[dim]no devices[/]")

    def show_scan(self, t: ScanTracker, session: Any, now_s: float) -> None:
        if not self.drawing():
            return
        state = session.session_state if session.scanning else t.shown_status
        lines = [f"state {state}"]
        if t.n_views:
            lines.append(f"views {t.views_done}/{t.n_views}")
            lines.append(f"frames {t.frames_done}/{t.frames_total}")
        if t.active:
            lines.append(f"step {escape(t.step)}")
            lines.append(f"ETA {t.eta_text(now_s)}")
        if t.points:
            lines.append(f"{t.points} points")
        show(self.query_one("#summary-scan", Static), "\n".join(lines))
