"""Printing for the commands."""

from __future__ import annotations

from rich.console import Console


def print_as_is(console: Console, text: str) -> None:
    """Print ``text`` as it is: no rich markup read from it (a path or name may hold ``[...]``)
    and no line break put inside it where the output is narrow (a pipe is 80 columns), so a
    path printed is a path a user or a script can copy."""
    console.print(text, markup=False, soft_wrap=True)
