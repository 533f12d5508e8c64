"""The footer with the keys of the focused panel: Textual's :class:`~textual.widgets.Footer`,
whose key widgets are made once per set of keys and shown again when that set comes back.

Textual's footer removes and mounts all its key widgets again whenever the screen's bindings
are refreshed — on every focus change (twice: the blur and the focus), also when the keys
stay the same. Each rebuild mounts and styles some ten to twenty widgets and lays the screen
out once more: a good part of the CPU of a tab switch, which over SSH is felt as a lag on every
F-key. Here each set of keys gets a row of key widgets the first time it is shown; switching
between tabs then only shows one row and hides another.
"""

from __future__ import annotations

from typing import Any

from textual.app import ComposeResult
from textual.compose import compose
from textual.containers import Horizontal
from textual.widgets import Footer
from textual.widgets._footer import FooterKey

#: Rows of key widgets kept for sets of keys not shown now (the least recently shown go first).
KEPT_ROWS = 12
#: Keys shown first, whatever the tab adds after them: at 80 columns the keys that do not fit
#: are cut at the right (the stop key was, on the Rig tab, under the palette's key).
FIRST_ACTIONS = ("stop",)


def stop_key_first(widgets: list[Any]) -> list[Any]:
    """The footer's key widgets with those of :data:`FIRST_ACTIONS` moved to the front."""
    first = [w for w in widgets if isinstance(w, FooterKey) and w.action in FIRST_ACTIONS]
    return first + [w for w in widgets if w not in first]


class KeyRow(Horizontal):
    """The footer's key widgets for one set of keys (Footer's own layout, one line)."""

    DEFAULT_CSS = "KeyRow { width: 1fr; height: 1; }"

    def __init__(self, *children: Any, keys: tuple[Any, ...]) -> None:
        super().__init__(*children)
        self.keys = keys
        self.shown_at = 0  # when it was shown last (the footer's count of key changes)


class KeysFooter(Footer):
    """A :class:`~textual.widgets.Footer` that keeps a row of key widgets per set of keys."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self._shown: tuple[Any, ...] | None = None  # the keys of the row shown now
        self._changes = 0

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
        if not self._bindings_ready:
            return
        self._shown = self.shown_keys()
        yield KeyRow(*stop_key_first(compose(self, super().compose())), keys=self._shown)

    async def recompose(self) -> None:
        if not self.is_attached or self._shown is None:
            await super().recompose()  # the first keys: Footer composes them (compose above)
            return
        keys = self.shown_keys()
        if keys == self._shown:
            return  # the same keys: keep the widgets showing them
        self._shown = keys
        self._changes += 1
        rows = list(self.query_children(KeyRow))
        row = next((r for r in rows if r.keys == keys), None)
        if row is None:
            hidden = sorted((r for r in rows if not r.display), key=lambda r: r.shown_at)
            if len(hidden) >= KEPT_ROWS:
                rows.remove(hidden[0])
                await hidden[0].remove()
            row = KeyRow(*stop_key_first(compose(self, super().compose())), keys=keys)
            row.display = False
            await self.mount(row)
        row.shown_at = self._changes
        for r in rows:
            r.display = r is row
        row.display = True
