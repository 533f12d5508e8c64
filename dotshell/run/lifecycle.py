"""A run's lifecycle: who may write it (a lock), what its recorded state means, and signals.

* :class:`RunLock` — an exclusive ``flock`` on ``<run>/.lock`` held by the one process writing
  the run (a scan, a re-processing job). A second writer is refused with who holds it. The lock
  dies with its process, so a run whose manifest says ``running`` but whose lock is free was
  left by a process that is gone: every command reports it as ``interrupted``.
* :func:`interrupts` — SIGINT, SIGTERM and SIGHUP raise :class:`Interrupted` in the main
  thread (the first one only: cleanup is never cut short by a second signal), after calling
  the stop callbacks registered with :func:`on_interrupt` (the rig's ``stop()``, so a moving
  stage halts at once, before the stack unwinds). A third signal exits at once; the run is then
  found ``interrupted`` by the next command.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import signal
import socket
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterator

from dotshell.errors import Interrupted, RunError
from dotshell.run.layout import RunLayout
from dotshell.runtime.locks import holder, try_flock

#: Final states; ``running`` is the only other one.
FINAL_STATES = ("completed", "failed", "aborted", "interrupted")
LOCK_NAME = RunLayout.LOCK


def interrupt_reason(exc: BaseException) -> str:
    return exc.reason if isinstance(exc, Interrupted) else "stopped by Ctrl-C (SIGINT)"


# ---- the lock ----------------------------------------------------------------------------------

class RunLock:
    """Exclusive advisory lock of one run directory (see the module docstring)."""

    def __init__(self, root: Path | str) -> None:
        self.root = Path(root)
        self.path = self.root / LOCK_NAME
        self._fd: int | None = None

    def acquire(self, command: str) -> None:
        """Take the lock for ``command`` or raise :class:`RunError` naming the holder."""
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as exc:
            if exc.errno not in (errno.EROFS, errno.EACCES, errno.EPERM):
                raise
            raise RunError(f"{self.root} cannot be written ({exc.strerror}): a command that "
                           "processes a run writes its results into it. Copy the run somewhere "
                           "writable (`cp -a RUN DEST`) and run the command on the copy.") from None
        if not try_flock(fd):
            raise RunError(f"{self.root} is being written by {describe_holder(read_holder(self.path))}; "
                           "wait for it to finish (`dotshell inspect RUN` shows it), or stop it, "
                           "then try again.") from None
        info = {"pid": os.getpid(), "host": socket.gethostname(), "command": command,
                "since": time.strftime("%Y-%m-%dT%H:%M:%S")}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(info).encode(), 0)
        self._fd = fd

    def release(self) -> None:
        if self._fd is not None:
            try:
                os.ftruncate(self._fd, 0)
            finally:
                fcntl.flock(self._fd, fcntl.LOCK_UN)
                os.close(self._fd)
                self._fd = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def __enter__(self) -> RunLock:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.release()


def read_holder(path: Path) -> dict[str, Any]:
    try:
        return json.loads(Path(path).read_text() or "{}")
    except (OSError, ValueError):
        return {}


def describe_holder(info: dict[str, Any]) -> str:
    if not info:
        return "another process"
    return (f"`dotshell {info.get('command', '?')}` (pid {info.get('pid', '?')} on "
            f"{info.get('host', '?')}, since {info.get('since', '?')})")


def lock_holder(root: Path | str) -> dict[str, Any] | None:
    """Who holds ``root``'s lock (``{}`` if unknown), or None if nobody does."""
    return holder(Path(root) / LOCK_NAME)


def effective_status(root: Path | str, manifest: dict[str, Any]) -> tuple[str, str]:
    """(status, reason) as it truly is: a ``running`` run whose writer is gone is
    ``interrupted``."""
    status = str(manifest.get("status", "unknown"))
    reason = str(manifest.get("reason") or "")
    if status == "running" and lock_holder(root) is None:
        job = manifest.get("job") or {}
        return "interrupted", (f"the process writing it (`dotshell {job.get('command', '?')}`, "
                               f"pid {job.get('pid', '?')}) ended without finishing: killed, "
                               "crashed or the machine stopped")
    return status, reason


# ---- signals -----------------------------------------------------------------------------------

_callbacks: list[Callable[[], None]] = []
_callbacks_lock = threading.Lock()


@contextmanager
def on_interrupt(callback: Callable[[], None]) -> Iterator[None]:
    """Call ``callback`` (e.g. ``rig.stop``) as soon as a stop signal arrives, while inside."""
    with _callbacks_lock:
        _callbacks.append(callback)
    try:
        yield
    finally:
        with _callbacks_lock:
            if callback in _callbacks:
                _callbacks.remove(callback)


@contextmanager
def connected(rig: Any, close: bool = True) -> Iterator[Any]:
    """``rig`` (a :class:`dotshell.rig.assembly.Rig`) connected, its ``stop`` registered for stop
    signals *before* the first device connects — so Ctrl-C, SIGTERM and SIGHUP stop a stage
    homing at connect — and closed afterwards (also when connecting was interrupted) when
    ``close``."""
    with on_interrupt(rig.stop):
        try:
            rig.connect()
            yield rig
        finally:
            if close:
                rig.close()


def run_stop_callbacks() -> None:
    """Call every registered stop callback; never raises."""
    with _callbacks_lock:
        callbacks = list(_callbacks)
    for cb in callbacks:
        try:
            cb()
        except Exception:  # stopping must reach every device
            pass


class _Deferral(threading.local):
    depth = 0
    pending: str | None = None


_deferral = _Deferral()


@contextmanager
def signals_deferred() -> Iterator[None]:
    """Inside, a stop signal does not raise :class:`Interrupted` at once but when the block
    ends: for queue and condition operations of the main thread that an exception raised in
    their middle would corrupt (a ``Condition.notify`` cut short loses the wake-up of a waiting
    thread, e.g. the frame writer, and the process then hangs for ever)."""
    _deferral.depth += 1
    try:
        yield
    finally:
        _deferral.depth -= 1
        if _deferral.depth == 0 and _deferral.pending is not None:
            name, _deferral.pending = _deferral.pending, None
            raise Interrupted(name)


class _Handler:
    def __init__(self, notify: Callable[[str], None]) -> None:
        self.count = 0
        self.notify = notify

    def __call__(self, signum: int, frame: Any) -> None:
        name = signal.Signals(signum).name
        self.count += 1
        if self.count == 1:
            run_stop_callbacks()
            if _deferral.depth:  # raised when the protected block ends
                _deferral.pending = name
                return
            raise Interrupted(name)
        if self.count == 2:
            self.notify(f"{name}: still stopping — devices are being stopped and frames saved. "
                        "Send it once more to quit at once (the run is then reported "
                        "interrupted).")
            return
        os._exit(128 + signum)


@contextmanager
def interrupts(notify: Callable[[str], None] | None = None) -> Iterator[None]:
    """Turn SIGINT, SIGTERM and SIGHUP into one :class:`Interrupted` (main thread only;
    elsewhere this does nothing)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    handler = _Handler(notify or (lambda text: print(text, file=sys.stderr)))
    previous = {}
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        previous[sig] = signal.signal(sig, handler)
    try:
        yield
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)
