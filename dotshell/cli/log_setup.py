"""The command's log level (``-v``, ``-q``, ``--log-level``) on stdlib :mod:`logging`, and
third-party warnings kept off the terminal unless ``-v``.

Scan events (progress, messages) are not log records: they are shown by the front ends as
before. What goes through :mod:`logging` — device log lines (``dotshell.devices``), Dask's and
other libraries' loggers, and Python warnings (captured into the ``py.warnings`` logger) — is
printed to stderr at or above the chosen level: ``WARNING`` by default, ``INFO`` with ``-v``,
``DEBUG`` with ``-vv``, ``ERROR`` with ``-q``. Warnings (a library's ``DeprecationWarning`` or
PyVista's deprecation notices, say) are for developers: they are shown only with ``-v`` or a
``--log-level`` of ``INFO`` or below.
"""

from __future__ import annotations

import argparse
import logging
import sys
from typing import Any

LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")


class StderrHandler(logging.StreamHandler):
    """Writes to the current ``sys.stderr`` (tests swap it); device log lines
    (``dotshell.devices``), which the front ends already show as events, only when verbose."""

    verbose = False

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self):  # noqa: D102
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass

    def filter(self, record: logging.LogRecord) -> bool:
        if record.name.startswith("dotshell.devices") and not self.verbose:
            return False
        return bool(super().filter(record))


def add_logging_args(p: argparse.ArgumentParser, default: Any = None) -> None:
    """``-v``/``--verbose`` (repeatable), ``-q``/``--quiet`` and ``--log-level LEVEL``;
    ``default=argparse.SUPPRESS`` for a command's parser (the flags may follow the command
    without resetting what was given before it)."""
    keep = default is argparse.SUPPRESS
    p.add_argument("-v", "--verbose", action="count", default=default if keep else 0,
                   help="more log output: -v shows INFO and library warnings, -vv DEBUG")
    p.add_argument("-q", "--quiet", action="store_true", default=default if keep else False,
                   help="only errors in the log output")
    p.add_argument("--log-level", choices=LEVELS, type=str.upper, metavar="LEVEL",
                   default=default, help=f"log level ({', '.join(LEVELS)}); overrides -v/-q")


def add_logging_args_to_commands(sub: argparse._SubParsersAction) -> None:
    """The log flags on every command too: ``dotshell scan P -v`` as well as ``dotshell -v
    scan P``."""
    for child in sub.choices.values():
        add_logging_args(child, argparse.SUPPRESS)


def chosen_level(verbose: int = 0, quiet: bool = False, log_level: str | None = None) -> int:
    """The logging level the flags ask for."""
    if log_level:
        return int(getattr(logging, log_level))
    if verbose:
        return logging.DEBUG if verbose > 1 else logging.INFO
    return logging.ERROR if quiet else logging.WARNING


def configure_logging(args: argparse.Namespace) -> int:
    """Set the root logger's level and stderr handler from ``args``; route warnings to the
    ``py.warnings`` logger, shown only at ``INFO`` or below. Returns the level."""
    level = chosen_level(getattr(args, "verbose", 0), getattr(args, "quiet", False),
                         getattr(args, "log_level", None))
    root = logging.getLogger()
    handler = next((h for h in root.handlers if isinstance(h, StderrHandler)), None)
    if handler is None:
        handler = StderrHandler()
        handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
        root.addHandler(handler)
    handler.verbose = level <= logging.INFO
    # the handler holds the chosen level too: a library that sets its own logger's level lower
    # (Dask sets ``distributed`` to INFO and, finding this handler on the root, propagates to
    # it) would otherwise print every INFO line, tracebacks included, at the default level
    handler.setLevel(level)
    root.setLevel(level)
    logging.captureWarnings(True)
    logging.getLogger("py.warnings").setLevel(logging.WARNING if level <= logging.INFO
                                              else logging.CRITICAL + 1)
    return level
