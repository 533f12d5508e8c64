"""A job in a Python process of its own: what must not share the calling process's memory.

``run_in_child(func, *args)`` runs ``func(*args)`` in a new Python process
(``python -m dotshell.runtime.child``) and returns its result or raises what it raised. The
child holds none of the caller's memory, and what the job allocates goes back to the system
when it ends. Two jobs use it: the mesh stage (reading the cloud, the meshers, writing the
meshes: :mod:`dotshell.pipeline.mesh_process`; a scan that meshes at its end peaks at the larger
of its own memory and the mesher's, not their sum, issue 33) and compiling the numba kernels a
run needs (:mod:`dotshell.pipeline.kernel_warmup`: the compiler's memory never joins the
scan's). A new interpreter rather than ``multiprocessing``'s spawn: spawn runs the caller's
main script again, which breaks scripts without an ``if __name__ == "__main__"`` guard.

The parent writes the child's ``sys.path``, what it imports at once (``warm_up``: a process
started early, while the caller prepares its job, imports the job's libraries meanwhile) and
then ``(func, args, job name)`` pickled to its stdin; a child whose input ends before a job exits. The
child writes back ``(True, result)`` or ``(False, exception)`` pickled on its stdout (a
:class:`~dotshell.errors.DotshellError` unchanged, any other with the child's traceback added as
a note); whatever the libraries print goes to its stderr, which the parent logs (DEBUG). A
child that dies without a word — killed by the system when memory runs out, or a crash in
compiled code — is a :class:`ChildProcessLost` naming its exit code or signal and the end of
its stderr. An interrupted parent (Ctrl-C, a stop) ends the child before returning.
"""

from __future__ import annotations

import logging
import os
import pickle
import signal
import subprocess
import sys
import traceback
from collections.abc import Callable
from typing import Any

from dotshell.errors import DotshellError

log = logging.getLogger(__name__)


class ChildProcessLost(DotshellError):
    """A job's process ended without a result: killed (the system out of memory) or crashed.
    ``job`` names the job, ``ending`` says how the process ended ('killed by SIGKILL', 'exit
    code 3') and ``tail`` holds the last lines it wrote."""

    def __init__(self, job: str, ending: str, tail: str) -> None:
        self.job, self.ending, self.tail = job, ending, tail
        super().__init__(f"the {job} process ended without a result ({ending}): the system may "
                         "have stopped it for lack of memory, or it crashed."
                         + (f" Its last words:\n{tail}" if tail else ""))

    def __reduce__(self) -> tuple[Any, ...]:  # crosses processes (a batch's workers) whole
        return (type(self), (self.job, self.ending, self.tail))


class ChildProcess:
    """A new Python process (``python -m dotshell.runtime.child``) that imports ``warm_up`` at
    once and then waits for one job (:meth:`run`)."""

    def __init__(self, warm_up: tuple[str, ...] = ()) -> None:
        # (this module imports no numpy: `dotshell mesh` starts its process first thing, and
        # importing numpy before it took 0.1 s off the process's head start)
        self.proc = subprocess.Popen([sys.executable, "-m", __name__], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        assert self.proc.stdin is not None
        self.proc.stdin.write(pickle.dumps(list(sys.path)) + pickle.dumps(tuple(warm_up)))
        self.proc.stdin.flush()

    def run(self, func: Callable[..., Any], *args: Any, job: str = "job") -> Any:
        """``func(*args)`` in the process (see :func:`run_in_child`); ``job`` names it in the
        log and in the error of a process that died."""
        proc = self.proc
        try:
            out, err = proc.communicate(pickle.dumps((func, args, job)))
        finally:
            if proc.poll() is None:  # interrupted while waiting: do not leave the job running
                proc.kill()
                proc.wait()
        text = err.decode(errors="replace").strip()
        if text:
            log.debug("%s process (pid %d) wrote:\n%s", job, proc.pid, text)
        try:
            ok, value = pickle.loads(out)
        except Exception:
            raise ChildProcessLost(job, _ending(proc.returncode),
                                   "\n".join(text.splitlines()[-5:])) from None
        if ok:
            return value
        raise value

    def discard(self) -> None:
        """End the process without a job: it holds nothing but what it imported, so it is
        killed rather than left to finish its imports (a command that fails at once, a user's
        error, ends at once)."""
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.communicate()


def run_in_child(func: Callable[..., Any], *args: Any, job: str = "job",
                 process: ChildProcess | None = None) -> Any:
    """``func(*args)`` in a new Python process (``process``, one started earlier, if given);
    its return value, or the exception it raised. ``func`` and ``args`` must pickle
    (module-level functions, plain data, objects of importable classes); :func:`picklable`
    checks.

    Raises:
        ChildProcessLost: the process ended without a result (killed, crashed), with its exit
            code or signal; whatever ``func`` raised, otherwise.
    """
    return (process or ChildProcess()).run(func, *args, job=job)


def picklable(*objects: Any) -> bool:
    """Whether ``objects`` can be handed to :func:`run_in_child` (a plugin's mesher may hold
    things that cannot, such as a lambda)."""
    try:
        pickle.dumps(objects)
    except Exception:
        return False
    return True


def _ending(returncode: int | None) -> str:
    """How a process ended, in words: 'killed by SIGKILL' or 'exit code 3'."""
    if returncode is not None and returncode < 0:
        try:
            return f"killed by {signal.Signals(-returncode).name}"
        except ValueError:
            return f"killed by signal {-returncode}"
    return f"exit code {returncode}"


def _child_main() -> None:
    """The child: read the job, configure the process as the ``dotshell`` command does, run,
    write the outcome on the original stdout (everything else printed goes to stderr)."""
    import faulthandler

    result = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    faulthandler.enable()
    sys.path[:] = pickle.load(sys.stdin.buffer)
    # pyvista imports mypy's plugin interface whenever mypy is installed (a development venv):
    # 35 modules, 0.04 s of CPU and 16 MiB here for nothing a mesher uses. A None entry makes
    # importlib.util.find_spec("mypy") answer None, as where mypy is not installed
    sys.modules.setdefault("mypy", None)  # type: ignore[arg-type]
    _warm_up(pickle.load(sys.stdin.buffer))
    job = "job"  # until the job's own name is read
    try:
        from dotshell.runtime.process import fix_mmap_threshold, limit_blas_threads

        try:
            func, args, job = pickle.load(sys.stdin.buffer)
        except EOFError:  # started early, and the caller ended without a job
            result.close()
            return
        limit_blas_threads()
        fix_mmap_threshold()
        outcome: tuple[bool, Any] = (True, func(*args))
    except BaseException as exc:  # noqa: BLE001 - every outcome goes back to the parent
        outcome = (False, _portable(exc, job))
    try:
        data = pickle.dumps(outcome)
    except Exception as exc:  # a result that does not pickle: say so rather than vanish
        data = pickle.dumps((False, _portable(exc, job)))
    result.write(data)
    result.close()
    # the parent reads stderr until it closes: ending without the interpreter's teardown
    # (freeing open3d's, VTK's and the meshes' objects: 0.13 s of CPU and wall at the end of
    # the demo's mesh step, on the command's critical path) hands the result over at once
    from dotshell.runtime.process import exit_now

    exit_now(0)


def _warm_up(names: tuple[str, ...]) -> None:
    """Import each "module" or call each "module:function" of ``names``; a failure is left for
    the job to meet and report."""
    import importlib

    for name in names:
        module, _, function = name.partition(":")
        try:
            loaded = importlib.import_module(module)
            if function:
                getattr(loaded, function)()
        except Exception:  # noqa: BLE001 - the job imports it again and reports it
            pass


def _portable(exc: BaseException, job: str) -> BaseException:
    """``exc`` as it can cross the pipe: itself (with the child's traceback as a note unless it
    is a dotshell error, whose message is for the user), or a RuntimeError with its text when
    it cannot be pickled."""
    from dotshell.errors import DotshellError

    if not isinstance(exc, DotshellError):
        exc.add_note(f"in the {job} process:\n" + "".join(traceback.format_exception(exc)))
    try:
        pickle.loads(pickle.dumps(exc))
    except Exception:
        return RuntimeError(f"{type(exc).__name__}: {exc}\n"
                            + "".join(traceback.format_exception(exc)))
    return exc


if __name__ == "__main__":
    _child_main()
