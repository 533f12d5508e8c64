"""The footer with the keys of the focused panel: Textual's :class:`~textual.widgets.Footer`,
rebuilt only when the keys it shows change.

Textual's footer removes and mounts all its key widgets again whenever the screen's bindings
are refreshed — on every focus change (twice: the blur and the focus), also when the keys
stay the same. Each rebuild mounts and styles some twenty widgets: about half the CPU of a
tab switch, which over SSH is felt as a lag on every F-key.
"""

from __future__ import annotations

from typing import Any

from textual.app import ComposeResult
from textual.widgets import Footer


class KeysFooter(Footer):
    """A :class:`~textual.widgets.Footer` that skips rebuilds which would show the same keys."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self._shown: tuple[Any, ...] | None = None  # what the key widgets were made from

    def shown_keys(self) -> tuple[Any, ...]:
        """Everything the footer's key widgets are made from: each of the screen's active
        bindings (the hidden ones too: the command palette's key is one), whether it is
        enabled, its tooltip, and the footer's own options."""
        keys = tuple((b.key, b.action, b.description, b.show, b.key_display, b.tooltip,
                      (b.group.description, b.group.compact) if b.group else None,
                      enabled, tooltip)
                     for _, b, enabled, tooltip in self.screen.active_bindings.values())
        return keys, self.compact, self.show_command_palette

    def compose(self) -> ComposeResult:
        self._shown = self.shown_keys() if self._bindings_ready else None
        yield from super().compose()

    async def recompose(self) -> None:
        if self.is_attached and self._shown is not None and self.shown_keys() == self._shown:
            return  # the same keys: keep the widgets showing them
        await super().recompose()
