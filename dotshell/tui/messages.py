"""Messages the client's reader thread and the worker threads post to the UI thread."""

from __future__ import annotations

from typing import Any

from textual.message import Message


class ServerMessage(Message):
    """A message the rig server pushed (``event``, ``state``, ``devices``, ``console``, ...;
    docs/server.md), or ``closed`` when the connection is gone."""

    def __init__(self, message: dict[str, Any]) -> None:
        super().__init__()
        self.message = message


class ActionDone(Message):
    """A session request run in a worker finished: ``error`` is its message or ``""``."""

    def __init__(self, label: str, result: Any = None, error: str = "") -> None:
        super().__init__()
        self.label = label
        self.result = result
        self.error = error
