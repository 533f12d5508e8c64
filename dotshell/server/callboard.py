"""The call board: which device calls the session worker is inside, readable by the server
without the worker's help.

A driver hung in C while holding the GIL stops every thread of its process, so the worker
cannot *say* what it is stuck in. Before each device call the worker writes "camera
(sim-camera) capture() since T" into a page of memory it shares with the server (a memfd
both map); the server reads it when the worker stops answering, and names the hung device.

Layout of the page: a sequence number (uint32, odd while a write is under way), the length of
the text (uint32), then the text: JSON ``{label: {"method": NAME, "since": UNIX_S}}`` of every
call in progress (a seqlock: the reader retries a torn read).
"""

from __future__ import annotations

import json
import mmap
import os
import struct
import threading
import time
from typing import Any

#: Bytes of the shared page; calls that do not fit are left out (the first ones stay).
SIZE = 4096
_HEAD = struct.Struct("<II")


class CallBoard:
    """One shared page; ``fd`` is a memfd to hand to the worker (``pass_fds``)."""

    def __init__(self, fd: int | None = None) -> None:
        if fd is None:
            fd = os.memfd_create("dotshell-callboard", 0)  # inherited only when passed
            os.ftruncate(fd, SIZE)
        self.fd = fd
        self._map = mmap.mmap(fd, SIZE)
        self._calls: dict[str, dict[str, Any]] = {}
        self._lock = threading.Lock()
        self._seq = _HEAD.unpack_from(self._map, 0)[0] & ~1

    # ---- the worker's side ------------------------------------------------------------------

    def enter(self, label: str, method: str, thread_id: int | None = None) -> None:
        """A call of ``label``'s ``method`` starts (label: ``camera (sim-camera)``) on the
        thread ``thread_id`` (native id)."""
        with self._lock:
            self._calls[label] = {"method": method, "since": time.time(), "tid": thread_id}
            self._publish()

    def leave(self, label: str) -> None:
        with self._lock:
            self._calls.pop(label, None)
            self._publish()

    def _publish(self) -> None:
        data = json.dumps(self._calls).encode()
        if len(data) > SIZE - _HEAD.size:
            data = b"{}"
        self._seq += 1  # odd: being written
        _HEAD.pack_into(self._map, 0, self._seq, 0)
        self._map[_HEAD.size:_HEAD.size + len(data)] = data
        self._seq += 1
        _HEAD.pack_into(self._map, 0, self._seq, len(data))

    # ---- the server's side ------------------------------------------------------------------

    def read(self) -> dict[str, dict[str, Any]]:
        """The calls in progress: ``{label: {"method": NAME, "since": UNIX_S}}``."""
        for _ in range(1000):
            seq, n = _HEAD.unpack_from(self._map, 0)
            if seq & 1:
                continue
            data = bytes(self._map[_HEAD.size:_HEAD.size + n])
            if _HEAD.unpack_from(self._map, 0)[0] == seq:
                try:
                    return json.loads(data) if data else {}
                except ValueError:
                    continue
        return {}

    def describe(self, pid: int | None = None, now_s: float | None = None) -> str:
        """The calls in progress as people read them, longest first ("" when none):
        ``camera (sim-camera) capture() for 12.3 s``. With the worker's ``pid``, a call whose
        thread sleeps on a futex while another's does not is only waiting (for the GIL the
        other holds, most likely) and is listed after it as such."""
        now_s = time.time() if now_s is None else now_s
        calls = sorted(self.read().items(), key=lambda kv: kv[1].get("since", now_s))
        waiting = {label for label, c in calls if pid and _on_futex(pid, c.get("tid"))}
        if len(waiting) == len(calls):
            waiting = set()  # nothing tells the culprit from the others: name them all

        def text(label: str, c: dict[str, Any]) -> str:
            return (f"{label} {c.get('method', '?')}() for "
                    f"{max(0.0, now_s - c.get('since', now_s)):.1f} s")

        shown = "; ".join(text(label, c) for label, c in calls if label not in waiting)
        others = ", ".join(text(label, c) for label, c in calls if label in waiting)
        return shown + (f" (waiting behind it: {others})" if others else "")

    def close(self) -> None:
        self._map.close()
        os.close(self.fd)


def _on_futex(pid: int, tid: Any) -> bool:
    """True when thread ``tid`` of ``pid`` sleeps in the kernel on a futex (a lock: the GIL, or
    a driver's own); False when not, or unknown (no /proc, the thread gone)."""
    if not isinstance(tid, int):
        return False
    try:
        with open(f"/proc/{pid}/task/{tid}/wchan", encoding="ascii") as f:
            return "futex" in f.read()
    except OSError:
        return False
