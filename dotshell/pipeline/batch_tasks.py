"""What a study batch runs on its Dask workers: the tasks of one run's job, each reading its
inputs from the run directory (frames, profile, calibration) and writing into the job's
unpublished generation — never the lock, the manifest's state or the publication, which stay
with the job in the client process (:mod:`dotshell.pipeline.batch`).

* :func:`head_task` — the steps before the views (a new calibration), once per run;
* :func:`view_task` — decode and triangulate one view (:func:`~dotshell.pipeline.steps.
  reconstruct_one_view`); the frames are read here, from the run, never sent to the worker;
* :func:`tail_task` — the views' gathering and every step after it (merge, validation,
  previews, mesh, normalize, exports), once per run.

Each returns a :class:`TaskOutcome`: its value, the events it emitted (replayed by the client
onto the run's event log), its wall seconds and the bytes it read, for the study's figures.
"""

from __future__ import annotations

import os
import socket
import time
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable

from dotshell import __version__
from dotshell.errors import RunError
from dotshell.events import Event, EventBus
from dotshell.geometry.calibration import RigCalibration
from dotshell.pipeline.engine import JobWork, StepsDone, outcome_of, run_steps
from dotshell.run.generations import ProductStore
from dotshell.run.layout import RunLayout
from dotshell.pipeline.steps import make_coding, reconstruct_one_view
from dotshell.plugins import get_plugin_manager
from dotshell.profile.loader import Profile
from dotshell.run.store import RunStore, versions


@dataclass
class TaskOutcome:
    """One finished task: ``kind`` is ``head``, ``view`` or ``tail``; ``seconds`` its wall time
    on the worker; ``read_bytes`` what it read from files (``rchar`` of ``/proc/self/io``;
    None where the OS does not count it); ``value`` a view's report record or the
    :class:`~dotshell.pipeline.engine.StepsDone` of a head or tail."""

    run: str
    kind: str
    view: int | None
    value: Any
    seconds: float
    read_bytes: int | None
    worker: str
    events: list[Event] = field(default_factory=list)
    #: what failed the task (a one-paragraph :class:`~dotshell.errors.RunError`), or None. A
    #: task never raises for its run's own faults: an exception travelling through Dask made
    #: it cancel and retry tasks of healthy runs (issue 33); the client fails the run alone.
    error: RunError | None = None


def identity() -> dict[str, str]:
    """What a worker must share with the client: dotshell's version, its plugins' versions
    and which plugins fail to load (loading them here also readies a worker for its tasks)."""
    errors = sorted(f"{e.name} ({e.reason})" for e in get_plugin_manager().load_errors)
    return {"dotshell": __version__,
            **{k: v for k, v in versions().items() if k.startswith("plugin:")},
            "plugins failing to load": "; ".join(errors) or "none"}


def missing_runs(roots: list[str]) -> list[str]:
    """The run directories of ``roots`` this worker cannot see (no ``manifest.json``)."""
    return [r for r in roots if not (Path(r) / RunLayout.MANIFEST).is_file()]


def executing_keys(dask_worker: Any) -> list[str]:
    """The keys of the tasks this worker is running, including cancelled ones still running
    (a cancelled task's function is not stopped: it runs to its end)."""
    return [str(ts.key) for ts in dask_worker.state.executing]


@lru_cache(maxsize=1)
def _configure_worker() -> None:
    """The ``dotshell`` command's process settings (BLAS on one thread, the heap's mmap
    threshold), once per worker process."""
    from dotshell.runtime.process import configure_process

    configure_process()


def _read_bytes() -> int | None:
    try:
        with open("/proc/self/io", "rb") as f:
            for line in f:
                if line.startswith(b"rchar:"):
                    return int(line.split()[1])
    except OSError:
        pass
    return None


def _measured(run_root: Path, kind: str, view: int | None,
              body: Callable[[EventBus], Any], client_version: str) -> TaskOutcome:
    """Run ``body(bus)`` on this worker, collecting its events, seconds and bytes read."""
    if client_version != __version__:
        raise RunError(f"worker {socket.gethostname()} (pid {os.getpid()}) runs dotshell "
                       f"{__version__} but the batch was started with {client_version}; install "
                       "the same dotshell version on every worker (docs/batch.md).")
    _configure_worker()
    events: list[Event] = []
    bus = EventBus()
    bus.subscribe(events.append)
    r0, t0 = _read_bytes(), time.perf_counter()
    error = None
    try:
        value = body(bus)
    except Exception as exc:  # the run's own fault: reported in the outcome, never raised
        value, error = None, RunError(outcome_of(exc)[1])
    seconds = time.perf_counter() - t0
    r1 = _read_bytes()
    return TaskOutcome(run_root.name, kind, view, value, seconds,
                       None if r0 is None or r1 is None else r1 - r0,
                       f"{socket.gethostname()}:{os.getpid()}", events, error)


def _failed_before(run_root: Path, kind: str, view: int | None,
                   inputs: list[TaskOutcome | None]) -> TaskOutcome | None:
    """The outcome of a task whose input task failed: that failure, passed on unrun."""
    for o in inputs:
        if o is not None and o.error is not None:
            return TaskOutcome(run_root.name, kind, view, None, 0.0, 0, o.worker, [], o.error)
    return None


def _profile(run_root: Path) -> Profile:
    """The run's own profile (read and validated once per worker process and run)."""
    try:
        stamp = (run_root / RunLayout.PROFILE).stat().st_mtime_ns
    except OSError:
        stamp = 0  # load_run_profile says what is wrong
    return _profile_as_of(run_root, stamp)


@lru_cache(maxsize=16)
def _profile_as_of(run_root: Path, stamp: int) -> Profile:
    from dotshell.pipeline.scan import load_run_profile

    return load_run_profile(RunStore(run_root), get_plugin_manager())


def head_task(work: JobWork, names: list[str], client_version: str) -> TaskOutcome:
    """The steps of ``work`` before the views (``names``)."""
    return _measured(work.run_root, "head", None, lambda bus: run_steps(
        work, _profile(work.run_root), get_plugin_manager(), bus, names), client_version)


def view_task(work: JobWork, view: int, angle_deg: float, client_version: str,
              after: TaskOutcome | None = None) -> TaskOutcome:
    """Decode and triangulate ``view`` of ``work``'s run into its generation, reading the
    frames from the run here. ``after``: the head task's outcome, when the generation's
    calibration is made by it (only an ordering dependency)."""
    def body(bus: EventBus) -> dict[str, Any]:
        pm = get_plugin_manager()
        profile = _profile(work.run_root)
        run = RunStore(work.run_root)
        store = ProductStore(run, work.generation_of(run).dir)
        calib = RigCalibration.load(store.path(RunLayout.CALIBRATION))
        return reconstruct_one_view(store, view, angle_deg, profile, make_coding(profile, pm),
                                    calib, bus)

    failed = _failed_before(work.run_root, "view", view, [after])
    return failed or _measured(work.run_root, "view", view, body, client_version)


def tail_task(work: JobWork, names: list[str], client_version: str,
              head: TaskOutcome | None, views: list[TaskOutcome]) -> TaskOutcome:
    """The steps of ``work`` from the views on (``names``), with the views already made by
    :func:`view_task`: their files in the generation are the ``views`` product."""
    def body(bus: EventBus) -> StepsDone:
        run = RunStore(work.run_root)
        assigned = {f for files in work.files.values() for f in files}
        if head is not None:
            assigned |= {f for files in head.value.files.values() for f in files}
        extra = {"reconstructed": {o.view: o.value for o in views},
                 "prewritten": {"views": work.generation_of(run).listing() - assigned}}
        done = run_steps(work, _profile(work.run_root), get_plugin_manager(), bus, names, extra)
        if views and "reconstruct" in done.timings:  # the views' own time, not the gathering's
            done.timings["reconstruct"] = sum(o.seconds for o in views)
        return done

    failed = _failed_before(work.run_root, "tail", None, [head, *views])
    return failed or _measured(work.run_root, "tail", None, body, client_version)
