"""Colours that mark state on every terminal: a theme for terminals with 16 colours, and
``NO_COLOR`` honoured without turning colours into greys.

Textual's dark theme is made for true colour. Reduced to a 16-colour palette its accent (the
headings, the footer's keys) and its warning colour become bright red, the colour of errors.
:func:`few_colours_theme` is the same theme with its state colours on the ANSI palette itself:
accent cyan, warning yellow, error red, success green — each a different colour number.

With ``NO_COLOR`` set Textual turns every colour into a grey of its luminance (its Monochrome
filter), so red error text is darker — fainter — than ordinary text. :func:`no_color_ansi`
makes the app strip colours instead (Textual's NoColor filter): text keeps the terminal's own
colour, and states are marked by words and attributes (errors are bold).
"""

from __future__ import annotations

import dataclasses
import os

from textual.theme import BUILTIN_THEMES, Theme

FEW_COLOURS_THEME = "dotshell-16"
#: Colour systems of terminals with at most 16 colours (Rich's names).
FEW_COLOURS = ("standard", "windows")


def few_colours_theme() -> Theme:
    """textual-dark with accent, warning, error and success on distinct ANSI colours."""
    return dataclasses.replace(BUILTIN_THEMES["textual-dark"], name=FEW_COLOURS_THEME,
                               accent="#00AAAA", warning="#AAAA00", error="#AA0000",
                               success="#00AA00")


def no_color_ansi() -> bool | None:
    """``ansi_color`` for :class:`textual.app.App`: True under ``NO_COLOR`` (Textual then
    removes colours rather than greying them), else None (the theme decides)."""
    return True if os.environ.get("NO_COLOR") is not None else None
