"""Messages the session's worker threads post to the UI thread."""

from __future__ import annotations

from typing import Any

from textual.message import Message

from dotshell.events import Event


class SessionEvent(Message):
    """An event published on the session's bus (from any thread)."""

    def __init__(self, event: Event) -> None:
        super().__init__()
        self.event = event


class DeviceRows(Message):
    """A fresh device-status snapshot: ``Session.devices()`` rows, read off the UI thread."""

    def __init__(self, rows: list[dict[str, Any]]) -> None:
        super().__init__()
        self.rows = rows


class ActionDone(Message):
    """A session action run in a worker finished: ``error`` is its message or ``""``."""

    def __init__(self, label: str, result: Any = None, error: str = "") -> None:
        super().__init__()
        self.label = label
        self.result = result
        self.error = error
