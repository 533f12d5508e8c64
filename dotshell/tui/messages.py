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


class ServerBatch(Message):
    """Messages of the server wait in the app's inbox. At most one of these is queued at a
    time, so a key pressed during a busy scan is handled after one batch, not after every
    message the server pushed before it (the stop key came seconds late in a real terminal)."""


class ActionDone(Message):
    """A session request run in a worker finished: ``error`` is its message or ``""``."""

    def __init__(self, label: str, result: Any = None, error: str = "") -> None:
        super().__init__()
        self.label = label
        self.result = result
        self.error = error
