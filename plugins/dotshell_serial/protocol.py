"""Protocol-level tests of a serial driver, no pty needed: the driver's :class:`SerialLink`
talks to a :class:`ScriptedPort` that expects the requests of a script, in order, and answers
each with its reply::

    from dotshell_serial.protocol import scripted

    stage = MyStage({"port": "unused", ...}, RigContext())
    with scripted(stage, [(b"ID?\\n", b"ID RT-1 SN1234 FW2.0\\r\\n"),
                          (b"POS?\\n", b"POS 0.000 IDLE\\r\\n")]) as port:
        stage.connect()
    # leaving the block fails unless every exchange happened

A request is bytes (matched exactly) or a compiled ``re.Pattern`` of bytes, matched against
one line the driver wrote (up to and including its ``\\n``) — for message ids and numbers that
vary. A driver that writes something else fails at once with an AssertionError naming the
exchange it expected and what it got; a reply that is not there reads as silence (the driver's
DeviceTimeout, at once: nothing waits).
"""

from __future__ import annotations

import re
from contextlib import contextmanager
from typing import Any, Iterator, Sequence, Union

Request = Union[bytes, "re.Pattern[bytes]"]


class ScriptedPort:
    """Stands in for the ``serial.Serial`` a :class:`~dotshell_serial.link.SerialLink` holds.

    Attributes:
        written: every byte string the driver wrote, in order.
        done: how many exchanges happened.
    """

    def __init__(self, script: Sequence[tuple[Request, bytes]]) -> None:
        self.script = list(script)
        self.done = 0
        self.written: list[bytes] = []
        self.timeout: float | None = None
        self.rts = False
        self._pending = b""
        self._replies = b""
        self._open = True

    # ---- what pyserial offers and SerialLink uses ------------------------------------------------

    @property
    def is_open(self) -> bool:
        return self._open

    @property
    def in_waiting(self) -> int:
        return len(self._replies)

    def write(self, data: bytes) -> int:
        self.written.append(bytes(data))
        self._pending += bytes(data)
        self._match()
        return len(data)

    def flush(self) -> None:
        pass

    def read_until(self, end: bytes = b"\n") -> bytes:
        cut = self._replies.find(end)
        n = len(self._replies) if cut < 0 else cut + len(end)
        out, self._replies = self._replies[:n], self._replies[n:]
        return out

    def read(self, size: int = 1) -> bytes:
        out, self._replies = self._replies[:size], self._replies[size:]
        return out

    def reset_input_buffer(self) -> None:
        self._replies = b""

    def reset_output_buffer(self) -> None:
        pass

    def close(self) -> None:
        self._open = False

    # ---- the script ------------------------------------------------------------------------------

    def _match(self) -> None:
        while self._pending:
            if self.done >= len(self.script):
                raise AssertionError(f"the driver sent {self._pending!r} after the script's "
                                     f"{len(self.script)} exchanges ended")
            request, reply = self.script[self.done]
            if isinstance(request, re.Pattern):
                end = self._pending.find(b"\n")
                if end < 0:
                    return  # the line is not complete yet
                line, rest = self._pending[:end + 1], self._pending[end + 1:]
                if request.fullmatch(line) is None:
                    self._mismatch(request.pattern, line)
            elif self._pending.startswith(request):
                rest = self._pending[len(request):]
            elif request.startswith(self._pending):
                return  # the request is still being written
            else:
                self._mismatch(request, self._pending)
            self._pending = rest
            self._replies += reply
            self.done += 1

    def _mismatch(self, expected: Any, got: bytes) -> None:
        raise AssertionError(f"exchange {self.done + 1} of {len(self.script)}: the driver sent "
                             f"{got!r} where the script expects {expected!r}")

    def assert_done(self) -> None:
        """Fail unless every exchange of the script happened."""
        if self.done < len(self.script):
            left = [r.pattern if isinstance(r, re.Pattern) else r
                    for r, _ in self.script[self.done:]]
            raise AssertionError(f"{len(left)} exchange(s) of the script never happened; the "
                                 f"next expected request was {left[0]!r}")


@contextmanager
def scripted(device: Any, script: Sequence[tuple[Request, bytes]]) -> Iterator[ScriptedPort]:
    """Run ``device`` (anything with a ``link``: a :class:`~dotshell_serial.base.SerialDevice`)
    against ``script`` inside the block: opening its link attaches a :class:`ScriptedPort`
    instead of a serial port. The block fails unless the whole script happened."""
    link = device.link
    port = ScriptedPort(script)

    def open_scripted() -> None:
        link.path = "scripted port"
        link.serial = port

    link.open = open_scripted  # type: ignore[method-assign]
    try:
        yield port
    finally:
        del link.open
    port.assert_done()
