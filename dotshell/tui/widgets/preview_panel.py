"""The Preview panel: the latest frame, decoded column map or cloud rendering, drawn in the
terminal with its aspect ratio, with the path of the PNG it was read from and — for frames —
the raw frame's minimum, maximum, mean, saturated share and histogram. ``←``/``→`` step through
the previews of this session. Only small copies are kept (the PNGs stay on disk)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from PIL import Image as PILImage
from rich.markup import escape
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Container, Vertical
from textual.events import Resize
from textual.widgets import Sparkline, Static

from dotshell.session.console import PreviewSaved
from dotshell.events import Event
from dotshell.tui.redraw import DrawnWhileShown, show
from dotshell.tui.text import shown_path
from dotshell.tui.widgets.image_view import cell_aspect, fit_cells, image_widget

KIND_TITLES = {"snap": "snapshot", "frame": "latest frame", "columns": "decoded columns",
               "cloud": "cloud"}
#: Previews kept for browsing, and the longest side of the copy kept of each (pixels).
KEEP = 30
THUMBNAIL_PX = 512


@dataclass
class PreviewItem:
    kind: str
    path: str
    view: int
    image: PILImage.Image
    size: tuple[int, int]
    stats: dict[str, Any] = field(default_factory=dict)


def describe_stats(stats: dict[str, Any]) -> str:
    """``min 12 · max 4095 · mean 446 DN · 0.12 % saturated (4095)``."""
    if not stats:
        return ""
    sat = stats["saturated_pct"]
    style = "bold red" if sat >= 1.0 else "yellow" if sat > 0 else ""
    sat_text = f"{sat:.2f} % saturated (≥ {stats['full_scale']:g})"
    return (f"min {stats['min']:g} · max {stats['max']:g} · mean {stats['mean']:.0f} DN · "
            + (f"[{style}]{sat_text}[/]" if style else sat_text))


class PreviewPanel(DrawnWhileShown, Vertical, can_focus=True):
    """Shows one preview at a time; keeps the session's latest previews for browsing. A preview
    that comes while the Preview tab is hidden is read and kept at once and its title written;
    its image and histogram are drawn when the tab is shown."""

    BINDINGS = [Binding("left", "step(-1)", "Previous"), Binding("right", "step(1)", "Next")]

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.items: list[PreviewItem] = []
        self.index = -1

    def compose(self) -> ComposeResult:
        yield Static("no preview yet — snap a frame (Rig: space) or run a scan",
                     id="preview-title")
        yield Static(id="preview-stats")
        yield Sparkline([], id="preview-histogram")
        with Container(id="preview-box"):
            yield image_widget(id="preview-image")

    @property
    def current(self) -> PreviewItem | None:
        return self.items[self.index] if 0 <= self.index < len(self.items) else None

    def handle_session_event(self, ev: Event) -> None:
        if isinstance(ev, PreviewSaved):
            self.add_preview(ev.kind, ev.path, ev.view, ev.stats)

    def add_preview(self, kind: str, path: str, view: int = -1,
                    stats: dict[str, Any] | None = None) -> None:
        """Read the PNG now (it may be overwritten later), keep a small copy and show it."""
        try:
            with PILImage.open(path) as im:
                size = im.size
                im.draft("RGB", (THUMBNAIL_PX, THUMBNAIL_PX))
                image = im.convert("RGB")
                image.thumbnail((THUMBNAIL_PX, THUMBNAIL_PX))
        except OSError as exc:
            show(self.query_one("#preview-title", Static),
                 f"[bold red]cannot read preview {escape(path)}: {escape(str(exc))}[/]")
            return
        self.items.append(PreviewItem(kind, path, view, image, size, dict(stats or {})))
        del self.items[:-KEEP]
        self.index = len(self.items) - 1
        self._show()

    def _show(self) -> None:
        item = self.current
        if item is None:
            return
        title = KIND_TITLES.get(item.kind, item.kind)
        if item.view >= 0:
            title += f" (view {item.view + 1})"
        colours = self.app.console.color_system
        warning = "" if colours == "truecolor" else (
            f"  [yellow]only {colours or 'no'} colours: the image is approximate[/]")
        show(self.query_one("#preview-title", Static),
             f"[b]{escape(title)}[/] {self.index + 1}/{len(self.items)}  "
             f"{item.size[0]}×{item.size[1]}  {escape(shown_path(item.path))}{warning}")
        show(self.query_one("#preview-stats", Static), describe_stats(item.stats))
        if self.drawing():
            self.redraw()

    def redraw(self) -> None:
        """The current preview's histogram and image (a new image lays the screen out and
        is converted for the terminal: not for a hidden tab)."""
        item = self.current
        if item is None:
            return
        histogram = self.query_one(Sparkline)
        histogram.data = item.stats.get("histogram") or []
        histogram.display = bool(item.stats.get("histogram"))
        self.query_one("#preview-image").image = item.image  # type: ignore[attr-defined]
        self._fit()

    def _fit(self) -> None:
        """Size the image's cells to the box, keeping the picture's aspect ratio."""
        item = self.current
        box = self.query_one("#preview-box").size
        if item is None or box.width == 0 or box.height == 0:
            return
        cols, rows = fit_cells(item.image.width, item.image.height, box.width, box.height,
                               cell_aspect())
        widget = self.query_one("#preview-image")
        widget.styles.width, widget.styles.height = cols, rows

    def on_resize(self, event: Resize) -> None:
        self.call_after_refresh(self._fit)

    def action_step(self, delta: int) -> None:
        if self.items:
            self.index = (self.index + delta) % len(self.items)
            self._show()
