"""The mesh stage's heavy part in a process of its own.

Reading the cloud, the surface and volume meshers (open3d, pyacvd, pymeshfix, TetGen) and
writing the meshes run in a new Python process (``python -m dotshell.pipeline.mesh_process``):
it holds none of the calling process's memory, and what the meshers allocate goes back to the
system when it ends. A scan that meshes at its end (``[mesh] after_scan``) therefore peaks at
the larger of its own memory and the mesher's, not their sum (issue 33: the agar scan peaked at
2.56 GB in the mesh step; docs/performance.md). A new interpreter rather than
``multiprocessing``'s spawn: spawn runs the caller's main script again, which breaks scripts
without an ``if __name__ == "__main__"`` guard.

The parent writes the child's ``sys.path``, what it imports at once (:data:`WARM_UP` for a
process :func:`start_early` started while the command prepares the job, nothing otherwise) and
then ``(func, args)`` pickled to its stdin; a child whose input ends before a job exits. The
child writes back ``(True, result)`` or ``(False, exception)`` pickled on its stdout (a
:class:`~dotshell.errors.DotshellError` such as MeshError unchanged, any other with the child's
traceback added as a note); whatever the libraries print goes to its stderr, which the parent
logs (DEBUG). A child that dies without a word — killed by the system when memory runs out, or a
crash in a mesher's compiled code — is a :class:`MeshError` naming its exit code or signal and
the end of its stderr. An interrupted parent (Ctrl-C, a stop) ends the child before returning.
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

log = logging.getLogger(__name__)


#: What the default meshers import, in a fresh process 0.62-0.65 s of CPU at load 8
#: (dotshell's mesh stage 0.09 s, open3d 0.29 s without its plotly drawing, pyvista and pyacvd
#: 0.25 s; 1.14 s with open3d's plotly drawing and scipy.ndimage, issue 32's second round): a
#: mesh process started early (:func:`start_early`) imports them while the command prepares
#: the job. "module" or
#: "module:function" (a function called without arguments: open3d needs its libusb loaded
#: first, and its plotly drawing deferred, :func:`dotshell.runtime.compat.import_open3d`).
WARM_UP = ("dotshell.pipeline.mesh", "dotshell.runtime.compat:import_open3d", "pyvista",
           "pyacvd", "pymeshfix", "tetgen")


class MeshProcess:
    """A new Python process (``python -m dotshell.pipeline.mesh_process``) that imports
    ``warm_up`` at once and then waits for one job (:meth:`run`)."""

    def __init__(self, warm_up: tuple[str, ...] = ()) -> None:
        # (this module imports no numpy: `dotshell mesh` starts the process first thing, and
        # importing numpy before it took 0.1 s off the process's head start)
        self.proc = subprocess.Popen([sys.executable, "-m", __name__], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        assert self.proc.stdin is not None
        self.proc.stdin.write(pickle.dumps(list(sys.path)) + pickle.dumps(tuple(warm_up)))
        self.proc.stdin.flush()

    def run(self, func: Callable[..., Any], *args: Any, job: str = "mesh") -> Any:
        """``func(*args)`` in the process (see :func:`run_in_child`); ``job`` names it in the
        error of a process that died (``"mesh"``: with the advice on the mesh's size)."""
        proc = self.proc
        try:
            out, err = proc.communicate(pickle.dumps((func, args)))
        finally:
            if proc.poll() is None:  # interrupted while waiting: do not leave the mesher running
                proc.kill()
                proc.wait()
        text = err.decode(errors="replace").strip()
        if text:
            log.debug("mesh process (pid %d) wrote:\n%s", proc.pid, text)
        try:
            ok, value = pickle.loads(out)
        except Exception:
            from dotshell.fem.meshes import MeshError

            tail = "\n".join(text.splitlines()[-5:])
            advice = (" or a mesher crashed. Try a larger node distance ([mesh] "
                      "node_distance_mm or --node-distance), or free memory, and run "
                      "`dotshell mesh RUN` again." if job == "mesh" else " or it crashed.")
            raise MeshError(f"the {job} process ended without a result "
                            f"({_ending(proc.returncode)}): the system may have stopped it for "
                            f"lack of memory,{advice}"
                            + (f" Its last words:\n{tail}" if tail else "")) from None
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


#: the process :func:`start_early` started, until a job takes it or it is discarded
_early: MeshProcess | None = None


def start_early(warm_up: tuple[str, ...] = WARM_UP) -> MeshProcess:
    """Start the next mesh process now, importing ``warm_up`` while the caller prepares its
    job (``dotshell mesh`` calls it first thing: on two cores the command's own start-up, the
    run's lock and plan overlap the mesher's imports); :func:`run_in_child` hands it the first
    job. Call :func:`discard_early` when no job may come."""
    global _early
    if _early is None:
        _early = MeshProcess(warm_up)
    return _early


def discard_early() -> None:
    """End the process :func:`start_early` started if no job took it."""
    global _early
    early, _early = _early, None
    if early is not None:
        early.discard()


def run_in_child(func: Callable[..., Any], *args: Any, job: str = "mesh") -> Any:
    """``func(*args)`` in a new Python process (the one :func:`start_early` started, if any);
    its return value, or the exception it raised. ``func`` and ``args`` must pickle
    (module-level functions, plain data, objects of importable classes); :func:`picklable`
    checks.

    Raises:
        MeshError: the process ended without a result (killed, crashed), with its exit code
            or signal; whatever ``func`` raised, otherwise.
    """
    global _early
    process, _early = (_early or MeshProcess()), None
    return process.run(func, *args, job=job)


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
    try:
        from dotshell.runtime.process import fix_mmap_threshold, limit_blas_threads

        try:
            func, args = pickle.load(sys.stdin.buffer)
        except EOFError:  # started early, and the caller ended without a job
            result.close()
            return
        limit_blas_threads()
        fix_mmap_threshold()
        outcome: tuple[bool, Any] = (True, func(*args))
    except BaseException as exc:  # noqa: BLE001 - every outcome goes back to the parent
        outcome = (False, _portable(exc))
    try:
        data = pickle.dumps(outcome)
    except Exception as exc:  # a result that does not pickle: say so rather than vanish
        data = pickle.dumps((False, _portable(exc)))
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


def _portable(exc: BaseException) -> BaseException:
    """``exc`` as it can cross the pipe: itself (with the child's traceback as a note unless it
    is a dotshell error, whose message is for the user), or a RuntimeError with its text when
    it cannot be pickled."""
    from dotshell.errors import DotshellError

    if not isinstance(exc, DotshellError):
        exc.add_note("in the mesh process:\n" + "".join(traceback.format_exception(exc)))
    try:
        pickle.loads(pickle.dumps(exc))
    except Exception:
        return RuntimeError(f"{type(exc).__name__}: {exc}\n"
                            + "".join(traceback.format_exception(exc)))
    return exc


if __name__ == "__main__":
    _child_main()
