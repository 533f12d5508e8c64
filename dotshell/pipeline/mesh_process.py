"""The mesh stage's heavy part in a process of its own (:mod:`dotshell.runtime.child`).

Reading the cloud, the surface and volume meshers (open3d, pyacvd, pymeshfix, TetGen) and
writing the meshes run in a new Python process: it holds none of the calling process's memory,
and what the meshers allocate goes back to the system when it ends. A scan that meshes at its
end (``[mesh] after_scan``) therefore peaks at the larger of its own memory and the mesher's,
not their sum (issue 33: the agar scan peaked at 2.56 GB in the mesh step;
docs/performance.md). ``dotshell mesh`` starts that process first thing (:func:`start_early`),
so that the meshers' imports overlap the command's own start-up; a process that dies without a
result is a :class:`~dotshell.fem.meshes.MeshError` with the advice a mesh's size calls for.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from dotshell.runtime.child import ChildProcess, ChildProcessLost, picklable

__all__ = ["WARM_UP", "discard_early", "picklable", "run_in_child", "start_early"]

#: What the default meshers import, in a fresh process 0.62-0.65 s of CPU at load 8
#: (dotshell's mesh stage 0.09 s, open3d 0.29 s without its plotly drawing, pyvista and pyacvd
#: 0.25 s; 1.14 s with open3d's plotly drawing and scipy.ndimage, issue 32's second round): a
#: mesh process started early (:func:`start_early`) imports them while the command prepares
#: the job. "module" or
#: "module:function" (a function called without arguments: open3d needs its libusb loaded
#: first, and its plotly drawing deferred, :func:`dotshell.runtime.compat.import_open3d`).
WARM_UP = ("dotshell.pipeline.mesh", "dotshell.runtime.compat:import_open3d", "pyvista",
           "pyacvd", "pymeshfix", "tetgen")

#: the process :func:`start_early` started, until a job takes it or it is discarded
_early: ChildProcess | None = None


def start_early(warm_up: tuple[str, ...] = WARM_UP) -> ChildProcess:
    """Start the next mesh process now, importing ``warm_up`` while the caller prepares its
    job (``dotshell mesh`` calls it first thing: on two cores the command's own start-up, the
    run's lock and plan overlap the mesher's imports); :func:`run_in_child` hands it the first
    job. Call :func:`discard_early` when no job may come."""
    global _early
    if _early is None:
        _early = ChildProcess(warm_up)
    return _early


def discard_early() -> None:
    """End the process :func:`start_early` started if no job took it."""
    global _early
    early, _early = _early, None
    if early is not None:
        early.discard()


def run_in_child(func: Callable[..., Any], *args: Any) -> Any:
    """``func(*args)`` in the mesh process (the one :func:`start_early` started, if any; else
    a new one): :func:`dotshell.runtime.child.run_in_child`.

    Raises:
        MeshError: the process ended without a result (killed, crashed), with its exit code
            or signal and what to try; whatever ``func`` raised, otherwise.
    """
    global _early
    process, _early = _early, None
    try:
        return (process or ChildProcess()).run(func, *args, job="mesh")
    except ChildProcessLost as lost:
        from dotshell.fem.meshes import MeshError

        raise MeshError(
            f"the mesh process ended without a result ({lost.ending}): the system may have "
            "stopped it for lack of memory, or a mesher crashed. Try a larger node distance "
            "([mesh] node_distance_mm or --node-distance), or free memory, and run "
            "`dotshell mesh RUN` again." + (f" Its last words:\n{lost.tail}" if lost.tail
                                             else "")) from None
