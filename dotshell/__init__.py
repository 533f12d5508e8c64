"""dotshell — instrument shell for structured-light surface scanning on DOT rigs."""

from __future__ import annotations

from typing import Any

from dotshell.runtime import moved as _moved

__version__ = "0.1.0"

_moved.install()  # old module paths keep working one release (dotshell.runtime.moved)


def __getattr__(name: str) -> Any:
    """``dotshell.hookimpl``, the decorator for plugin hook implementations
    (``@dotshell.hookimpl``), made at first use: importing pluggy costs ~60 ms that
    ``dotshell --version`` does not need (:mod:`dotshell.cli.entry`)."""
    if name == "hookimpl":
        import pluggy

        globals()["hookimpl"] = marker = pluggy.HookimplMarker("dotshell")
        return marker
    raise AttributeError(f"module 'dotshell' has no attribute {name!r}")
