"""Key repeat on the jog keys collapsed into few moves: while one move is under way, further
presses add up into one pending move, sent when the first is done — so 20 rapid presses make
two moves (the first step, then the other 19 steps at once), never a queue of 20 that keeps the
stage turning after the key is let go. The stop key drops what is pending."""

from __future__ import annotations

from typing import Callable


class JogQueue:
    """``send(degrees)`` starts one relative move; call :meth:`done` when it has finished."""

    def __init__(self, send: Callable[[float], None]) -> None:
        self.send = send
        self.pending_deg = 0.0
        self.moving = False

    def press(self, degrees: float) -> None:
        if self.moving:
            self.pending_deg += degrees
            return
        self.moving = True
        self.send(degrees)

    def done(self) -> None:
        """The move under way ended (reached, failed or stopped): send what piled up."""
        pending, self.pending_deg = self.pending_deg, 0.0
        if pending:
            self.send(pending)
        else:
            self.moving = False

    def cancel(self) -> None:
        """Forget the presses not yet sent (the stop key)."""
        self.pending_deg = 0.0
