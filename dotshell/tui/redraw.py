"""Redrawing only what changed, and only what is on screen. The app shows the server's state
again on every message it pushes (state, device status, each scan event), and Textual's
``Static.update`` lays the whole screen out and repaints, even when the text is the same, the
widget keeps its size, or it sits on a tab that is not shown: most of those updates change
nothing the user sees, and each layout costs some milliseconds (felt over SSH as stutter)."""

from __future__ import annotations

from textual.visual import VisualType
from textual.widget import Widget
from textual.widgets import Static


def show(widget: Static, content: VisualType) -> None:
    """:func:`update` unless the widget shows that markup string already (other content, such
    as Rich renderables, is always redrawn)."""
    if not (isinstance(content, str) and isinstance(widget.content, str)
            and widget.content == content):
        update(widget, content)


def update(widget: Static, content: VisualType) -> None:
    """``widget.update(content)``, repainting only the widget when its size cannot change:
    its width is not set by its content (nor is an enclosing width) and its height is fixed or
    the new content is exactly as many lines tall as the widget was last laid out. Otherwise
    (and before the widget was ever laid out) the screen is laid out again, as
    ``Static.update`` does. The test is against the laid-out size, not the content shown
    before: that content may never have been laid out (drawn again before the layout ran)."""
    size = widget.content_size
    height = widget.styles.height
    widget.update(content, layout=False)
    if size.width <= 0 or _width_follows_content(widget) or (
            (height is None or height.is_auto)
            and _content_height(widget, size.width) != size.height):
        lay_out(widget)


def lay_out(widget: Widget) -> None:
    """``widget.refresh(layout=True)``, sizing the widget by the content it has now. Textual
    keeps the size it computed for a widget (its box model) under a counter that
    ``refresh(layout=True)`` advances only when no layout of the widget is pending yet. Content
    changed while one was pending, after a screen layout for another widget's sake had sized
    this one by its older content, was laid out at the older size: the Rig tab's device table
    kept an empty list's two lines and showed one device of three (a loaded machine's
    interleaving, ``Static.update`` alike). Advancing the counter here makes that size stale."""
    widget._layout_updates += 1
    widget.refresh(layout=True)


def _width_follows_content(widget: Widget) -> bool:
    node: Widget | None = widget
    while isinstance(node, Widget):
        width = node.styles.width
        if width is not None and width.is_auto:
            return True
        node = node.parent if isinstance(node.parent, Widget) else None
    return False


def _content_height(widget: Widget, width: int) -> int:
    """Lines the widget's content takes at ``width`` cells (what a layout would give it)."""
    return widget.get_content_height(widget.container_size, widget.app.size, width)


def is_shown(widget: Widget) -> bool:
    """Whether neither the widget nor an enclosing one has ``display: none`` (a tab that is not
    shown, the sidebar in a narrow terminal). A dialog over the screen does not hide it."""
    node: Widget | None = widget
    while isinstance(node, Widget):
        if not node.display:
            return False
        node = node.parent if isinstance(node.parent, Widget) else None
    return True


class DrawnWhileShown:
    """Mixin for a widget that draws only while it is shown. A draw asked for while it is
    hidden marks it stale (:meth:`drawing`); :meth:`catch_up` draws it from the latest state
    once it is shown again — the app calls it when it switches to the widget's tab, before the
    screen is laid out and painted (no frame shows stale content); the ``Show`` event Textual
    sends after the layout does it otherwise (the sidebar coming back in a wider terminal)."""

    stale = False

    def drawing(self) -> bool:
        """True when a draw should happen now; False (and stale) while hidden."""
        if is_shown(self):  # type: ignore[arg-type]
            return True
        self.stale = True
        return False

    def catch_up(self) -> None:
        """Draw what was missed while hidden (nothing if nothing was, or still hidden)."""
        if self.stale and is_shown(self):  # type: ignore[arg-type]
            self.stale = False
            self.redraw()

    def redraw(self) -> None:
        """Draw everything from the latest state."""
        raise NotImplementedError

    def on_show(self) -> None:
        self.catch_up()
