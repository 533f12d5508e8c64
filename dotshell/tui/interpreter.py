"""The Python console's engine, independent of any widget: decides when input is complete,
runs it in a namespace (echoing the value of a final expression, like the REPL), routes the
running thread's ``print`` output to a callback, formats tracebacks without the engine's own
frames, and can interrupt a long call from another thread.
"""

from __future__ import annotations

import ast
import codeop
import ctypes
import io
import linecache
import sys
import threading
import traceback
from typing import Any, Callable

from dotshell.errors import DotshellError

#: ``write(kind, text)``: kind is ``out`` (stdout), ``err`` (stderr), ``result`` (the repr of
#: a final expression) or ``error`` (a formatted traceback).
Writer = Callable[[str, str], None]


def wants_more(source: str) -> bool:
    """True when ``source`` is an unfinished statement and Enter should add a line instead of
    running it: an open bracket or block, or an indented last line of a complete block (a
    blank line then runs it, as in the standard REPL)."""
    if not source.strip():
        return True
    lines = source.split("\n")
    try:
        code = codeop.compile_command(source, "<console>", "exec")
    except (SyntaxError, ValueError, OverflowError):
        return False  # run it: the error is shown
    if code is None:
        return True
    last = lines[-1]
    if not last.strip():
        return False  # a blank line ends the block
    return last[:1].isspace()


class _ThreadRouter(io.TextIOBase):
    """A ``sys.stdout``/``sys.stderr`` stand-in: writes from one thread go to a callback,
    everyone else's to the stream it replaced."""

    def __init__(self, fallback: Any, thread_id: int, write: Callable[[str], None]) -> None:
        self.fallback = fallback
        self.thread_id = thread_id
        self.sink = write

    def writable(self) -> bool:
        return True

    def write(self, text: str) -> int:
        if threading.get_ident() == self.thread_id:
            self.sink(text)
        elif self.fallback is not None:
            self.fallback.write(text)
        return len(text)

    def flush(self) -> None:
        if threading.get_ident() != self.thread_id and self.fallback is not None:
            self.fallback.flush()


class Interpreter:
    """Runs console input in ``namespace``; one input at a time.

    Args:
        namespace: the globals the input runs in (e.g. :meth:`dotshell.console.Session.namespace`).
        write: receives output as it is produced (from the running thread).
        on_interrupt: called by :meth:`interrupt` first; return True when it handled the
            interrupt (e.g. by aborting a running scan cleanly), False to interrupt the code.
    """

    def __init__(self, namespace: dict[str, Any], write: Writer,
                 on_interrupt: Callable[[], bool] | None = None) -> None:
        self.namespace = namespace
        self.write = write
        self.on_interrupt = on_interrupt
        self.history: list[str] = []
        self.count = 0
        self._thread_id: int | None = None
        self._guard = threading.Lock()  # interrupt() never targets a finished input

    @property
    def busy(self) -> bool:
        return self._thread_id is not None

    def run(self, source: str) -> bool:
        """Run ``source`` in the calling thread; True if it raised nothing."""
        try:
            return self._run(source)
        except KeyboardInterrupt:  # an interrupt that landed just as the input finished
            return False

    def _run(self, source: str) -> bool:
        if self._thread_id is not None:
            raise RuntimeError("the console is already running an input")
        self.history.append(source)
        self.count += 1
        filename = f"<console#{self.count}>"
        linecache.cache[filename] = (len(source), None, source.splitlines(True), filename)
        self._thread_id = threading.get_ident()
        out = _ThreadRouter(sys.stdout, self._thread_id, lambda t: self.write("out", t))
        err = _ThreadRouter(sys.stderr, self._thread_id, lambda t: self.write("err", t))
        sys.stdout, sys.stderr = out, err
        try:
            self._execute(source, filename)
            return True
        except BaseException as exc:  # the user's error, shown in the pane; the app lives on
            self.write("error", self.format_exception(exc))
            return False
        finally:
            with self._guard:
                self._thread_id = None
            if sys.stdout is out:
                sys.stdout = out.fallback
            if sys.stderr is err:
                sys.stderr = err.fallback

    def _execute(self, source: str, filename: str) -> None:
        tree = ast.parse(source, filename, "exec")
        last = tree.body[-1] if tree.body and isinstance(tree.body[-1], ast.Expr) else None
        body = ast.Module(body=tree.body[:-1] if last else tree.body, type_ignores=[])
        exec(compile(body, filename, "exec"), self.namespace)
        if last is not None:
            value = eval(compile(ast.Expression(last.value), filename, "eval"), self.namespace)
            if value is not None:
                self.namespace["_"] = value
                self.write("result", repr(value))

    def format_exception(self, exc: BaseException) -> str:
        """The traceback without the engine's frames; for a :class:`DotshellError` (an expected,
        user-fixable failure) only the console's own frames and the message."""
        if isinstance(exc, SyntaxError) and str(exc.filename).startswith("<console"):
            return "".join(traceback.format_exception_only(type(exc), exc))  # the input itself
        tb = exc.__traceback__
        while tb is not None and tb.tb_frame.f_code.co_filename == __file__:
            tb = tb.tb_next
        if isinstance(exc, DotshellError):
            frames = [f for f in traceback.extract_tb(tb) if f.filename.startswith("<console")]
            head = ["Traceback (most recent call last):\n", *traceback.format_list(frames)] \
                if frames else []
            return "".join(head + traceback.format_exception_only(type(exc), exc))
        return "".join(traceback.format_exception(type(exc), exc, tb))

    def interrupt(self) -> bool:
        """Interrupt the running input: first ``on_interrupt`` (a clean scan abort), else a
        ``KeyboardInterrupt`` raised in the running thread (delivered when it next runs Python
        code). False when nothing is running."""
        if self._thread_id is None:
            return False
        if self.on_interrupt is not None and self.on_interrupt():
            return True
        with self._guard:
            tid = self._thread_id
            if tid is None:
                return False
            ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(tid),
                                                       ctypes.py_object(KeyboardInterrupt))
        return True
