"""The Preview panel: the latest frame, decoded column map or cloud rendering, drawn in the
terminal, with the path of the PNG it was read from. ``←``/``→`` step through the previews
of this session."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from PIL import Image as PILImage
from rich.markup import escape
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Vertical
from textual.widgets import Static

from dotshell.console import PreviewSaved
from dotshell.events import Event
from dotshell.tui.text import short_path
from dotshell.tui.widgets.image_view import image_widget

KIND_TITLES = {"snap": "snapshot", "frame": "latest frame", "columns": "decoded columns",
               "cloud": "cloud"}


@dataclass
class PreviewItem:
    kind: str
    path: str
    view: int
    image: PILImage.Image


class PreviewPanel(Vertical, can_focus=True):
    """Shows one preview image at a time; keeps the session's previews for browsing."""

    BINDINGS = [Binding("left", "step(-1)", "Previous"), Binding("right", "step(1)", "Next")]

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.items: list[PreviewItem] = []
        self.index = -1

    def compose(self) -> ComposeResult:
        yield Static("no preview yet — snap a frame (Rig: space) or run a scan",
                     id="preview-title")
        yield image_widget(id="preview-image")

    @property
    def current(self) -> PreviewItem | None:
        return self.items[self.index] if 0 <= self.index < len(self.items) else None

    def handle_session_event(self, ev: Event) -> None:
        if isinstance(ev, PreviewSaved):
            self.add_preview(ev.kind, ev.path, ev.view)

    def add_preview(self, kind: str, path: str, view: int = -1) -> None:
        """Read the PNG now (it may be overwritten later) and show it."""
        try:
            with PILImage.open(path) as im:
                image = im.convert("RGB")
        except OSError as exc:
            self.query_one("#preview-title", Static).update(
                f"[red]cannot read preview {escape(path)}: {escape(str(exc))}[/]")
            return
        self.items.append(PreviewItem(kind, path, view, image))
        del self.items[:-50]
        self.index = len(self.items) - 1
        self._show()

    def _show(self) -> None:
        item = self.current
        if item is None:
            return
        title = KIND_TITLES.get(item.kind, item.kind)
        if item.view >= 0:
            title += f" (view {item.view})"
        self.query_one("#preview-title", Static).update(
            f"[b]{escape(title)}[/] {self.index + 1}/{len(self.items)}  "
            f"{item.image.width}×{item.image.height}  {escape(short_path(item.path))}")
        self.query_one("#preview-image").image = item.image  # type: ignore[attr-defined]

    def action_step(self, delta: int) -> None:
        if self.items:
            self.index = (self.index + delta) % len(self.items)
            self._show()
