"""Redrawing only what changed. The app shows the server's state again on every message it
pushes (state, device status, each scan event), and Textual's ``Static.update`` lays the whole
screen out and repaints even when the text is the same: most of those updates change nothing."""

from __future__ import annotations

from textual.visual import VisualType
from textual.widgets import Static


def show(widget: Static, content: VisualType) -> None:
    """``widget.update(content)`` unless it shows that markup string already (other content,
    such as Rich renderables, is always redrawn)."""
    if not (isinstance(content, str) and isinstance(widget.content, str)
            and widget.content == content):
        widget.update(content)
