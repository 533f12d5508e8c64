"""The Python console's engine, independent of any widget or socket: decides when input is
complete, runs it in a namespace (showing the value of a final expression, like the REPL),
routes the running thread's ``print`` output to a callback, serves its ``input()`` (and
``help()``, which reads with ``input()``) through a callback instead of the raw terminal, pages
``help(obj)`` into the output, completes names, formats tracebacks without the engine's own
frames, and can interrupt a long call from another thread.
"""

from __future__ import annotations

import ast
import codeop
import ctypes
import io
import linecache
import pydoc
import queue
import re
import rlcompleter
import sys
import threading
import traceback
from typing import Any, Callable

from dotshell.errors import DotshellError

#: ``write(kind, text)``: kind is ``out`` (stdout), ``err`` (stderr), ``result`` (the repr of
#: a final expression) or ``error`` (a formatted traceback).
Writer = Callable[[str, str], None]
_INTERRUPT = object()
_TOKEN = re.compile(r"[A-Za-z_][\w.]*$")


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
    """A ``sys.stdout``/``sys.stderr``/``sys.stdin`` stand-in: the console thread's writes go to
    a callback and its reads ask ``read_line``; every other thread uses the stream it replaced."""

    def __init__(self, fallback: Any, thread_id: int, write: Callable[[str], None] | None = None,
                 read_line: Callable[[], str] | None = None) -> None:
        self.fallback = fallback
        self.thread_id = thread_id
        self.sink = write
        self.source = read_line

    def _mine(self) -> bool:
        return threading.get_ident() == self.thread_id

    def writable(self) -> bool:
        return self.sink is not None

    def readable(self) -> bool:
        return self.source is not None

    def isatty(self) -> bool:
        return False if self._mine() else bool(self.fallback and self.fallback.isatty())

    def write(self, text: str) -> int:
        if self._mine() and self.sink is not None:
            self.sink(text)
        elif self.fallback is not None:
            self.fallback.write(text)
        return len(text)

    def readline(self, size: int | None = -1) -> str:  # type: ignore[override]  # typeshed: IOBase's bytes
        if self._mine() and self.source is not None:
            return self.source()
        return self.fallback.readline() if self.fallback is not None else ""

    def flush(self) -> None:
        if not self._mine() and self.fallback is not None:
            self.fallback.flush()


def _page(text: str) -> None:
    """``help(obj)`` output: written to stdout as plain text (the console pane scrolls)."""
    sys.stdout.write(pydoc.plain(text) + "\n")


class Interpreter:
    """Runs console input in ``namespace``; one input at a time.

    Args:
        namespace: the globals the input runs in (e.g. :meth:`dotshell.session.console.Session.namespace`).
        write: receives output as it is produced (from the running thread).
        on_interrupt: called by :meth:`interrupt` when the input is not waiting for a line;
            return True when it handled the interrupt (e.g. by aborting a running scan
            cleanly), False to interrupt the code.
        on_input: called (from the running thread) with the prompt when the input reads a
            line (``input()``, ``help()``); answer with :meth:`reply`.
        display: how the value of a final expression is shown (default ``repr``).
    """

    def __init__(self, namespace: dict[str, Any], write: Writer,
                 on_interrupt: Callable[[], bool] | None = None,
                 on_input: Callable[[str], None] | None = None,
                 display: Callable[[Any], str] = repr) -> None:
        self.namespace = namespace
        self.write = write
        self.on_interrupt = on_interrupt
        self.on_input = on_input
        self.display = display
        self.history: list[str] = []
        self.count = 0
        self.waiting_prompt: str | None = None
        self._partial_out = ""
        self._replies: queue.Queue[Any] = queue.Queue()
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
        self._thread_id = tid = threading.get_ident()
        self._partial_out = ""
        while not self._replies.empty():  # a reply or interrupt left over from the last input
            self._replies.get_nowait()
        out = _ThreadRouter(sys.stdout, tid, self._out)
        err = _ThreadRouter(sys.stderr, tid, lambda t: self.write("err", t))
        inp = _ThreadRouter(sys.stdin, tid, read_line=self._read_line)
        saved = sys.stdout, sys.stderr, sys.stdin, pydoc.pager
        sys.stdout, sys.stderr, sys.stdin, pydoc.pager = out, err, inp, _page
        try:
            self._execute(source, filename)
            return True
        except BaseException as exc:  # the user's error, shown in the pane; the app lives on
            self.write("error", self.format_exception(exc))
            return False
        finally:
            with self._guard:
                self._thread_id = None
            for name, mine, old in (("stdout", out, saved[0]), ("stderr", err, saved[1]),
                                    ("stdin", inp, saved[2])):
                if getattr(sys, name) is mine:
                    setattr(sys, name, old)
            pydoc.pager = saved[3]

    def _execute(self, source: str, filename: str) -> None:
        tree = ast.parse(source, filename, "exec")
        last = tree.body[-1] if tree.body and isinstance(tree.body[-1], ast.Expr) else None
        body = ast.Module(body=tree.body[:-1] if last else tree.body, type_ignores=[])
        exec(compile(body, filename, "exec"), self.namespace)
        if last is not None:
            value = eval(compile(ast.Expression(last.value), filename, "eval"), self.namespace)
            if value is not None:
                self.namespace["_"] = value
                self.write("result", self.display(value))

    # ---- input() --------------------------------------------------------------------------------

    def _out(self, text: str) -> None:
        self._partial_out = (self._partial_out + text).rpartition("\n")[2]
        self.write("out", text)

    def _read_line(self) -> str:
        """A line for the running input (its ``input()``): the prompt is what it printed last
        without a newline. KeyboardInterrupt when interrupted, EOFError on :meth:`reply` None."""
        prompt, self._partial_out = self._partial_out, ""
        self.waiting_prompt = prompt
        try:
            if self.on_input is not None:
                self.on_input(prompt)
            answer = self._replies.get() if self.on_input is not None else None
        finally:
            self.waiting_prompt = None
        if answer is _INTERRUPT:
            raise KeyboardInterrupt
        if answer is None:
            self.write("out", "\n")
            raise EOFError
        self.write("out", answer + "\n")  # the echo completes the prompt's line
        return answer + "\n"

    def reply(self, line: str | None) -> bool:
        """Answer the running input's ``input()`` with ``line`` (None: end of file); False
        when it is not waiting for one."""
        if self.waiting_prompt is None:
            return False
        self._replies.put(line)
        return True

    # ---- completion -------------------------------------------------------------------------------

    def complete(self, text: str) -> tuple[str, list[str]]:
        """The name or attribute being typed at the end of ``text`` and its completions (as
        :mod:`rlcompleter` gives them: ``(`` after callables, ``()`` after those without
        parameters), sorted, at most 200."""
        m = _TOKEN.search(text)
        token = m.group(0) if m else ""
        if not token:
            return "", []
        completer = rlcompleter.Completer(self.namespace)
        found: list[str] = []
        for state in range(1000):
            try:
                option = completer.complete(token, state)
            except Exception:  # evaluating the attribute chain failed: nothing to offer
                break
            if option is None:
                break
            if option not in found:
                found.append(option)
        return token, sorted(found)[:200]

    # ---- errors and interrupts ----------------------------------------------------------------------

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
        """Interrupt the running input: a pending ``input()`` raises KeyboardInterrupt; else
        ``on_interrupt`` (a clean scan abort); else a ``KeyboardInterrupt`` raised in the
        running thread (delivered when it next runs Python code). False when nothing runs."""
        if self._thread_id is None:
            return False
        if self.waiting_prompt is not None:
            self._replies.put(_INTERRUPT)
            return True
        if self.on_interrupt is not None and self.on_interrupt():
            return True
        with self._guard:
            tid = self._thread_id
            if tid is None:
                return False
            ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(tid),
                                                       ctypes.py_object(KeyboardInterrupt))
        return True
