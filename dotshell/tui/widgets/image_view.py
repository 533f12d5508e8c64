"""Images in the terminal. With textual-image installed: Kitty graphics or Sixel where the
terminal answers for them, coloured half-cell blocks otherwise. Without it (or with
``DOTSHELL_TUI_IMAGES=halfblock``): :class:`HalfBlockImage`, our own half-block drawing.

textual-image asks the terminal about its abilities when imported, which must happen before
the app takes over the terminal — importing this module does it.
"""

from __future__ import annotations

import os
from typing import Any

from PIL import Image as PILImage
from rich.console import Console, ConsoleOptions, RenderResult
from rich.segment import Segment
from rich.style import Style
from textual.widget import Widget

try:  # optional at run time: the fallback below draws half blocks itself
    from textual_image import renderable as _ti_renderable
    from textual_image.widget import HalfcellImage as _TIHalfcell
    from textual_image.widget import Image as _TIAuto
except Exception:  # ImportError, or a terminal query failing in an odd environment
    _ti_renderable = None  # type: ignore[assignment]  # mypy's idiom for a module that may be missing


def cell_aspect() -> float:
    """Height / width of a terminal cell (about 2); from the terminal when textual-image asked
    it, else 2."""
    if _ti_renderable is not None:
        try:
            from textual_image._terminal import get_cell_size

            size = get_cell_size()
            if size.width > 0 and size.height > 0:
                return size.height / size.width
        except Exception:  # no answer from the terminal: the usual shape
            pass
    return 2.0


def fit_cells(width_px: int, height_px: int, cols: int, rows: int,
              aspect: float = 2.0) -> tuple[int, int]:
    """The largest (columns, rows) of cells, at most ``cols`` × ``rows``, that show an image of
    ``width_px`` × ``height_px`` with its aspect ratio (cells ``aspect`` times taller than wide)."""
    if width_px <= 0 or height_px <= 0 or cols <= 0 or rows <= 0:
        return 0, 0
    scale = min(cols / width_px, rows * aspect / height_px)
    return (max(1, min(cols, round(width_px * scale))),
            max(1, min(rows, round(height_px * scale / aspect))))


def fit_size(width_px: int, height_px: int, cols: int, rows: int) -> tuple[int, int]:
    """Largest (columns, pixel rows) an image fits in with half blocks: each cell shows one
    pixel across and two down (terminal cells are about twice as tall as wide)."""
    if width_px <= 0 or height_px <= 0 or cols <= 0 or rows <= 0:
        return 0, 0
    scale = min(cols / width_px, 2 * rows / height_px)
    return max(1, int(width_px * scale)), max(2, int(height_px * scale) // 2 * 2)


class _HalfBlocks:
    """A Rich renderable: the image as rows of '▀' (top pixel = foreground, bottom = back)."""

    def __init__(self, image: PILImage.Image, cols: int, rows: int) -> None:
        self.image, self.cols, self.rows = image, cols, rows

    def __rich_console__(self, console: Console, options: ConsoleOptions) -> RenderResult:
        w, h = fit_size(self.image.width, self.image.height, self.cols, self.rows)
        if w == 0:
            return
        px = self.image.convert("RGB").resize((w, h), PILImage.Resampling.BOX).load()
        if px is None:  # PIL gives no pixel access only to images without pixels
            return
        for y in range(0, h, 2):
            for x in range(w):
                top, bottom = px[x, y], px[x, y + 1]
                yield Segment("▀", Style(color=f"rgb{top}", bgcolor=f"rgb{bottom}"))
            yield Segment.line()


class HalfBlockImage(Widget):
    """Draws a PIL image with half blocks, scaled to fit the widget."""

    DEFAULT_CSS = "HalfBlockImage { width: 1fr; height: 1fr; }"

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self._image: PILImage.Image | None = None

    @property
    def image(self) -> PILImage.Image | None:
        return self._image

    @image.setter
    def image(self, value: PILImage.Image | None) -> None:
        self._image = value
        self.refresh(layout=True)

    def render(self) -> Any:
        if self._image is None:
            return ""
        return _HalfBlocks(self._image, self.content_size.width, self.content_size.height)


def image_backend() -> str:
    """Which drawing the preview uses: ``sixel``, ``tgp``, ``halfcell`` (textual-image) or
    ``halfblock`` (ours)."""
    if _ti_renderable is None or os.environ.get("DOTSHELL_TUI_IMAGES") == "halfblock":
        return "halfblock"
    name = _ti_renderable.Image.__module__.rsplit(".", 1)[-1]
    return name if name in ("sixel", "tgp") else "halfcell"


def image_widget(**kwargs: Any) -> Widget:
    """The image widget for this terminal (an ``.image`` property takes a PIL image)."""
    backend = image_backend()
    if backend == "halfblock":
        return HalfBlockImage(**kwargs)
    if backend in ("sixel", "tgp"):
        return _TIAuto(**kwargs)
    return _TIHalfcell(**kwargs)
