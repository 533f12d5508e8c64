"""Study batches: re-process many runs as one Dask task graph (``dotshell batch``).

The client process (the one the user started) owns every run it works on: it takes the run's
lock, records the job (:class:`~dotshell.pipeline.engine.RunJob`), plans it and carries the
unchanged products over (:func:`~dotshell.pipeline.engine.prepare`), submits the job's tasks
(:mod:`dotshell.pipeline.batch_tasks`: a head task for a new calibration, one task per view for
decode + triangulate, one tail task for merge and everything after it) and, when they are
done, publishes the generation (:func:`~dotshell.pipeline.engine.publish`). Workers only read
the run directory and write into the job's unpublished generation, so a run's recorded state
is as true as after a single-run command, and a failure stays with its run.

A run counts as **finished** for a batch when its manifest's ``jobs`` history holds a
``completed`` job with this batch's key (:func:`batch_key`: the command and a digest of its
options and calibration file) whose generation is still the run's published one; a batch run
again skips finished runs, so a killed batch is completed by running it again.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
import uuid
from collections import deque
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

from dotshell.errors import DotshellError, RunError
from dotshell.events import Event, EventBus
from dotshell.pipeline.batch_tasks import (TaskOutcome, executing_keys, head_task, identity,
                                           missing_runs, tail_task, view_task)
from dotshell.pipeline.commands import check_calibration_for_run
from dotshell.pipeline.engine import JobWork, RunJob, outcome_of, prepare, publish
from dotshell.run.generations import current_number
from dotshell.run.layout import RunLayout
from dotshell.pipeline.steps import complete_views, view_angle
from dotshell.plugins import PluginManager
from dotshell.run.store import RunStore


#: seconds to wait for tasks that run on after their batch stopped (a view's decode and
#: triangulation takes seconds at full resolution, a run's tail a minute at most)
STRAGGLER_WAIT_S = 120.0


class BatchError(DotshellError):
    """The batch cannot start: no scheduler, workers that differ from the client, runs the
    workers cannot see."""


@dataclass(frozen=True)
class BatchCommand:
    """A re-processing command a batch runs on every run: the products it re-makes, without
    and with a new calibration (the same as the single-run command's)."""

    name: str
    targets: tuple[str, ...]
    targets_with_calibration: tuple[str, ...]


COMMANDS = {c.name: c for c in (
    BatchCommand("reconstruct", ("views",), ("calibration",)),
    BatchCommand("mesh", ("mesh", "exports"), ("calibration", "mesh", "exports")),
    BatchCommand("normalize", ("normalize",), ("calibration", "normalize")),
    BatchCommand("validate", ("validation",), ("calibration", "validation")),
)}


# ---- events --------------------------------------------------------------------------------

@dataclass(frozen=True)
class BatchStarted(Event):
    command: str
    runs: int
    skipped: int
    cluster: str
    workers: int


@dataclass(frozen=True)
class BatchTaskDone(Event):
    """A task finished: ``done`` of ``total`` tasks submitted so far (the total grows as runs
    are planned)."""

    run: str
    kind: str
    done: int
    total: int


@dataclass(frozen=True)
class BatchRunFinished(Event):
    """A run of the study ended: ``completed``, ``failed``, ``aborted`` or ``skipped``."""

    run: str
    status: str
    reason: str = ""
    summary: dict[str, Any] = field(default_factory=dict)


# ---- the study -----------------------------------------------------------------------------

@dataclass
class RunOutcome:
    """What the batch did to one run; ``tasks`` are the finished tasks' figures (their
    values and events dropped)."""

    run: Path
    status: str
    reason: str = ""
    report: dict[str, Any] = field(default_factory=dict)
    wall_s: float = 0.0
    tasks: list[TaskOutcome] = field(default_factory=list)

    @property
    def compute_s(self) -> float:
        """Seconds the run's tasks took on the workers, summed."""
        return sum(t.seconds for t in self.tasks)


def find_runs(patterns: list[str]) -> list[Path]:
    """The run directories named by ``patterns``, in order, each once: a run directory, a
    study directory (its sub-directories that are runs), or a glob (its matches that are runs;
    quote it so dotshell, not the shell, expands it). A directory that exists under the name
    given is taken as named, glob characters and all (``run[1]``). Absolute, symbolic links
    kept, so the paths are the ones workers see on a shared file system."""
    import glob

    runs: list[Path] = []
    for pattern in patterns:
        if any(c in pattern for c in "*?[") and not Path(pattern).exists():
            found = [Path(m) for m in sorted(glob.glob(pattern))]
            found = [p for p in found if (p / RunLayout.MANIFEST).is_file()]
            if not found:
                raise RunError(f"{pattern} matches no run directory (a directory holding "
                               "manifest.json); check the pattern and the current directory.")
        elif Path(pattern).is_dir() and not (Path(pattern) / RunLayout.MANIFEST).is_file():
            found = sorted(p for p in Path(pattern).iterdir() if (p / RunLayout.MANIFEST).is_file())
            if not found:
                raise RunError(f"{pattern} is neither a run directory nor a study directory "
                               "holding runs; give run directories, a study directory or a "
                               "glob such as 'runs/2026*'.")
        else:
            found = [RunStore.open(Path(pattern)).root]
        for path in found:
            p = path.absolute()
            if p not in runs:
                runs.append(p)
    return runs


def batch_key(command: str, options: dict[str, Any]) -> str:
    """``COMMAND:DIGEST`` — the command and a digest of its options, the calibration file by
    its content (so the same batch run again has the same key, a changed one another)."""
    opts = {k: v for k, v in sorted(options.items()) if v is not None}
    cal = opts.pop("calibration_file", None)
    if cal is not None:
        opts["calibration_sha256"] = hashlib.sha256(Path(cal).read_bytes()).hexdigest()
    digest = hashlib.sha256(json.dumps([command, opts], sort_keys=True).encode()).hexdigest()
    return f"{command}:{digest[:12]}"


def is_finished(store: RunStore, key: str) -> bool:
    """Whether ``key``'s batch finished this run and its products are still the published
    ones (see the module docstring)."""
    current = current_number(store.root)
    return current is not None and any(
        j.get("batch") == key and j.get("status") == "completed"
        and j.get("generation") == current for j in store.manifest.get("jobs", []))


# ---- the cluster ---------------------------------------------------------------------------

@contextmanager
def dask_client(scheduler: str | None = None, workers: int | None = None
                ) -> Iterator[tuple[Any, str]]:
    """A Dask client and a description of its cluster: the scheduler at ``scheduler``
    (``tcp://host:8786``), else a local cluster of ``workers`` processes (default: one per
    core), one thread each."""
    from distributed import Client

    if scheduler:
        try:
            client = Client(scheduler, timeout="20s", set_as_default=False)
        except (OSError, TimeoutError) as exc:
            raise BatchError(f"cannot reach the Dask scheduler at {scheduler} ({exc}); start "
                             "it (`dask scheduler`) and its workers (`dask worker ADDRESS`), "
                             "or leave out --scheduler for a local cluster.") from None
        try:
            yield client, f"scheduler {scheduler}"
        finally:
            client.close()
        return
    n = workers or os.cpu_count() or 1
    cluster = local_cluster(n)
    client = Client(cluster, set_as_default=False)
    try:
        yield client, f"local cluster of {n} worker process{'es' if n > 1 else ''}"
    finally:
        client.close()
        cluster.close()


#: dotshell's modules every batch worker imports for its tasks (the pipeline and numba: ~0.7 s
#: of CPU a worker); a local cluster's forkserver imports them once for all its workers
WORKER_MODULES = ("dotshell.pipeline.batch_tasks", "dotshell.pipeline.reconstruct",
                  "dotshell.pipeline.validate")


#: where a local cluster's scheduler serves its HTTP routes (health, metrics; no dashboard):
#: a free port of the loopback interface. Without it the scheduler takes port 8787 whatever
#: ``dashboard_address`` says, and a second cluster on the host (another batch, the test
#: suite's other worker) warns "Port 8787 is already in use" and moves elsewhere
SCHEDULER_HTTP_ADDRESS = "127.0.0.1:0"


def local_cluster(workers: int) -> Any:
    """A Dask ``LocalCluster`` of ``workers`` processes, one thread each, no dashboard (its
    scheduler's HTTP routes on a free loopback port, :data:`SCHEDULER_HTTP_ADDRESS`).

    Its workers are forked from a forkserver (where the platform has one and Dask's
    ``distributed.worker.multiprocessing-method`` is left at its default, ``spawn``): the
    forkserver imports Dask and :data:`WORKER_MODULES` once per process, later clusters start
    in ~1 s instead of ~5 s, and a worker ends without tearing its interpreter down (numba,
    VTK...: ~2.5 s of every cluster's close on 2 cores, now 0.2 s)."""
    import multiprocessing

    import dask
    from distributed import LocalCluster

    method = dask.config.get("distributed.worker.multiprocessing-method")
    if method == "spawn" and "forkserver" in multiprocessing.get_all_start_methods():
        method = "forkserver"
    with dask.config.set({"distributed.worker.multiprocessing-method": method}):
        if method == "forkserver":
            _preload_in_forkserver()
        return LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                            dashboard_address=None, silence_logs=worker_log_level(),
                            scheduler_kwargs={"dashboard_address": SCHEDULER_HTTP_ADDRESS})


def worker_log_level() -> int:
    """The level of a local cluster's worker processes' own log lines (printed straight to
    the terminal, not through this process's logging): CRITICAL, unless this process logs at
    INFO or below (``-v``), then that level. What a worker logs at ERROR is Dask's comm noise
    (under load a heartbeat that meets the closing scheduler, with its traceback); a run's
    fault reaches the batch through its task's outcome, a dead worker through its nanny, which
    logs in this process."""
    level = logging.getLogger().getEffectiveLevel()
    return level if level <= logging.INFO else logging.CRITICAL


def _preload_in_forkserver() -> None:
    """Add :data:`WORKER_MODULES` to the modules Dask has the forkserver import (they matter
    only before this process's forkserver starts; an import error there is ignored and met
    again by the worker's task, which reports it)."""
    import multiprocessing.forkserver as forkserver

    from distributed.utils import get_mp_context

    context = get_mp_context()  # sets Dask's own list, once per process
    dask_modules = list(getattr(forkserver._forkserver, "_preload_modules", None) or
                        ["distributed"])
    context.set_forkserver_preload(dask_modules + [m for m in WORKER_MODULES
                                                   if m not in dask_modules])


def check_workers(client: Any, runs: list[Path], wait_s: float = 60.0) -> int:
    """Refuse workers that run another dotshell (or plugin, Python, Dask) version than this
    process or cannot see the runs; returns the number of workers."""
    try:
        client.wait_for_workers(1, timeout=wait_s)
    except TimeoutError:
        raise BatchError(f"no Dask worker joined the scheduler within {wait_s:.0f} s; start "
                         "workers with `dask worker SCHEDULER_ADDRESS`.") from None
    try:
        client.get_versions(check=True)
    except ValueError as exc:
        raise BatchError(f"the Dask workers' Python packages differ from this process's: "
                         f"{exc}") from None
    mine, problems = identity(), []
    for worker, theirs in client.run(identity, on_error="return").items():
        if isinstance(theirs, BaseException):
            problems.append(f"{worker} cannot run dotshell ({type(theirs).__name__}: {theirs})")
        elif theirs != mine:
            diff = sorted(k for k in set(mine) | set(theirs) if mine.get(k) != theirs.get(k))
            problems.append(f"{worker} has " + ", ".join(
                f"{k} {theirs.get(k, 'missing')} (here {mine.get(k, 'missing')})" for k in diff))
    if problems:
        raise BatchError("workers differ from this dotshell: " + "; ".join(problems) +
                         ". Install the same dotshell and plugins on every worker "
                         "(docs/batch.md).")
    roots = [str(r) for r in runs]
    unseen = {w: m for w, m in client.run(missing_runs, roots).items() if m}
    if unseen:
        worker, missing = next(iter(unseen.items()))
        raise BatchError(f"worker {worker} cannot see {len(missing)} of the runs, e.g. "
                         f"{missing[0]}; put the study on a file system every worker mounts at "
                         "the same path (docs/batch.md).")
    return len(client.scheduler_info(n_workers=-1)["workers"])


def tasks_running_on(client: Any, runs: list[Path]) -> list[str]:
    """The runs of ``runs`` (names) a worker is still running a batch task of: a task goes on
    running after it is cancelled or its client is gone (a killed batch), and writes into its
    job's generation until it ends."""
    marks = {f"-{r.name}-g": r.name for r in runs}
    running = client.run(executing_keys, on_error="ignore")
    return sorted({name for keys in running.values() for key in keys
                   for mark, name in marks.items() if mark in key})


def wait_for_tasks(client: Any, runs: list[Path], timeout_s: float) -> list[str]:
    """Wait until no worker runs a task of ``runs`` (at most ``timeout_s``); returns the runs
    still busy then (none once the tasks ended). A scheduler that cannot be asked counts as
    idle: its workers are gone too."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            busy = tasks_running_on(client, runs)
        except Exception:  # noqa: BLE001 (a lost scheduler: nothing more to wait for)
            return []
        if not busy or time.monotonic() > deadline:
            return busy
        time.sleep(0.05)


# ---- the batch -----------------------------------------------------------------------------

@dataclass
class _ActiveRun:
    """A run whose job is open in this process and whose tasks are on the cluster."""

    job: RunJob
    work: JobWork
    futures: list[Any]
    outcomes: list[TaskOutcome] = field(default_factory=list)


class StudyBatch:
    """One ``dotshell batch COMMAND`` over a study (see the module docstring)."""

    def __init__(self, command: str, runs: list[Path], pm: PluginManager,
                 options: dict[str, Any] | None = None, bus: EventBus | None = None,
                 redo: bool = False) -> None:
        if command not in COMMANDS:
            raise RunError(f"unknown batch command {command!r}; known: {sorted(COMMANDS)}")
        self.command = COMMANDS[command]
        self.runs = runs
        self.pm = pm
        self.options = {k: v for k, v in (options or {}).items() if v is not None}
        self.calibration = self.options.get("calibration_file")
        self.key = batch_key(command, self.options)
        self.bus = bus or EventBus()
        self.redo = redo
        self.outcomes: dict[Path, RunOutcome] = {}
        self._done = 0
        self._total = 0
        self._token = uuid.uuid4().hex[:8]  # task keys unique to this batch
        self._version = ""

    @property
    def targets(self) -> tuple[str, ...]:
        c = self.command
        return c.targets_with_calibration if self.calibration else c.targets

    def run(self, client: Any, cluster: str = "", window: int | None = None
            ) -> list[RunOutcome]:
        """Process every unfinished run on ``client``'s cluster, at most ``window`` runs at a
        time (default: twice the workers; each open run holds its lock); returns one outcome
        per run, in the study's order."""
        workers = check_workers(client, self.runs)
        self._version = identity()["dotshell"]
        busy = wait_for_tasks(client, self.runs, STRAGGLER_WAIT_S)
        if busy:
            raise BatchError(f"the workers still run tasks of an earlier batch on {busy[0]} "
                             f"(and {len(busy) - 1} other runs) after {STRAGGLER_WAIT_S:.0f} s "
                             "(its client was killed; a task runs to its end); run the batch "
                             "again once they end.")
        todo = deque(r for r in self.runs if self.redo or not self._skip(r))
        self.bus.emit(BatchStarted(command=self.command.name, runs=len(self.runs),
                                   skipped=len(self.runs) - len(todo), cluster=cluster,
                                   workers=workers))
        self._loop(client, todo, window or 2 * workers)
        return [self.outcomes[r] for r in self.runs]

    def _skip(self, root: Path) -> bool:
        store = RunStore(root)
        try:
            if not is_finished(store, self.key):
                return False
        except DotshellError:  # a damaged manifest: the run's own job says what is wrong
            return False
        report = (store.read_json(RunLayout.REPORT) if store.path(RunLayout.REPORT).is_file()
                  else {})
        self._finish(RunOutcome(root, "skipped", "finished by an earlier run of this batch",
                                report))
        return True

    def _loop(self, client: Any, todo: deque[Path], window: int) -> None:
        from distributed import as_completed

        active: dict[Path, _ActiveRun] = {}
        owner: dict[str, Path] = {}
        pending = as_completed(loop=client.loop)
        try:
            while todo or active:
                while todo and len(active) < window:
                    root = todo.popleft()
                    run = self._start(client, root)
                    if run is not None:
                        active[root] = run
                        owner.update({f.key: root for f in run.futures})
                        pending.update(run.futures)
                if not active:
                    continue
                future = next(pending)
                root = owner.pop(future.key)
                if root in active:
                    self._collect(client, root, active, future)
        except BaseException as exc:  # Ctrl-C, SIGTERM, a lost scheduler: close every open job
            for run in active.values():
                client.cancel(run.futures)
            # a running task goes on writing into its job's generation: let it end first
            wait_for_tasks(client, list(active), STRAGGLER_WAIT_S)
            for run in active.values():
                self._close(run.job, exc, run.outcomes)
            raise

    def _start(self, client: Any, root: Path) -> _ActiveRun | None:
        """Open the run's job, plan it and submit its tasks; a run that cannot start fails
        alone (None)."""
        from dotshell.pipeline.scan import load_run_profile

        store = RunStore(root)  # a run gone since the batch started fails below, alone
        bus = EventBus()
        bus.subscribe(lambda ev: store.append_event(ev.to_dict()))
        try:
            profile = load_run_profile(store, self.pm)
            if self.calibration:
                check_calibration_for_run(self.calibration, store)
            job = RunJob(store, self.command.name, bus, batch=self.key).open()
        except Exception as exc:  # checked before anything is written: the run is unchanged
            store.close()
            self._finish(RunOutcome(root, *outcome_of(exc)))
            return None
        try:
            work = prepare(job, profile, self.pm, self.targets, self.options)
            futures = self._submit(client, work, store, self.runs.index(root))
        except BaseException as exc:
            self._close(job, exc)
            if not isinstance(exc, Exception):
                raise
            return None
        return _ActiveRun(job, work, futures)

    def _submit(self, client: Any, work: JobWork, store: RunStore, order: int) -> list[Any]:
        """The run's tasks: head (steps before the views), one per complete view, tail (the
        views' gathering and every step after). Earlier runs get higher priority, so runs
        finish in the study's order and a killed batch leaves few half-done."""
        version = self._version
        steps = work.steps
        split = steps.index("views") if "views" in steps else len(steps)
        head_names, tail_names = steps[:split], steps[split:]
        opts = {"priority": len(self.runs) - order, "pure": False}
        name = f"{order:04d}-{work.run_root.name}-g{work.generation:03d}-{self._token}"
        head = client.submit(head_task, work, head_names, version, key=f"head-{name}",
                             **opts) if head_names else None
        views = []
        if "views" in steps:
            views = [client.submit(view_task, work, v["index"], view_angle(v), version, head,
                                   key=f"view-{name}-{v['index']:03d}", **opts)
                     for v in complete_views(store)]  # not those marked lost
        tail = client.submit(tail_task, work, tail_names, version, head, views,
                             key=f"tail-{name}", **opts)
        futures = [f for f in (head, *views, tail) if f is not None]
        self._total += len(futures)
        return futures

    def _collect(self, client: Any, root: Path, active: dict[Path, _ActiveRun],
                 future: Any) -> None:
        """A task of an active run finished: replay its events; publish after the tail; fail
        the run (and cancel its other tasks) on an error."""
        run = active[root]
        self._done += 1
        if future.status != "finished":
            del active[root]
            exc = future.exception() if future.status == "error" else RunError(
                f"a task of {root.name} was cancelled by the cluster")
            for f in run.futures:  # the failed one is done: cancelling it again confused Dask
                if f is not future:
                    f.cancel()
            future.release()
            wait_for_tasks(client, [root], STRAGGLER_WAIT_S)  # its other running tasks
            self._total -= len(run.futures) - len(run.outcomes) - 1  # never to be done
            self._close(run.job, exc, run.outcomes)
            return
        outcome: TaskOutcome = future.result()
        for ev in outcome.events:
            run.job.bus.emit(ev)
        run.outcomes.append(outcome)
        self.bus.emit(BatchTaskDone(run=root.name, kind=outcome.kind, done=self._done,
                                    total=self._total))
        if outcome.kind != "tail":
            return
        del active[root]
        failed = next((o.error for o in run.outcomes if o.error is not None), None)
        if failed is not None:  # every task of the run has ended: nothing writes any more
            self._close(run.job, failed, run.outcomes)
            return
        try:
            parts = [o.value for o in run.outcomes if o.kind in ("head", "tail")]
            report = publish(run.job, run.work, parts)
        except BaseException as exc:
            self._close(run.job, exc, run.outcomes)
            if not isinstance(exc, Exception):
                raise
            return
        for o in run.outcomes:
            o.value, o.events = None, []
        self._close(run.job, None, run.outcomes, report)

    def _close(self, job: RunJob, exc: BaseException | None,
               tasks: list[TaskOutcome] | None = None,
               report: dict[str, Any] | None = None) -> None:
        """End ``job`` (``exc``: what ended it), release the run and record its outcome."""
        try:
            job.close(exc)
        finally:
            job.store.close()
        self._finish(RunOutcome(job.store.root, job.status or "failed", job.reason,
                                report or {}, _job_seconds(job), tasks or []))

    def _finish(self, outcome: RunOutcome) -> None:
        self.outcomes[outcome.run] = outcome
        self.bus.emit(BatchRunFinished(run=outcome.run.name, status=outcome.status,
                                       reason=outcome.reason, summary=summary_of(outcome)))


def _job_seconds(job: RunJob) -> float:
    jobs = job.store.manifest.get("jobs", [])
    return float(jobs[-1].get("seconds", 0.0)) if jobs else 0.0


def summary_of(outcome: RunOutcome) -> dict[str, Any]:
    """The figures a study table shows for one run (empty for a run without a report)."""
    rep = outcome.report
    if not rep:
        return {}
    v = rep.get("validation") or {}
    out: dict[str, Any] = {"generation": rep.get("generation"),
                           "views": len(rep.get("views", [])),
                           "points": (rep.get("cloud") or {}).get("points")}
    for k in ("mean_rel_error_pct", "std_rel_error_pct", "rms_radius_error_mm", "coverage_pct"):
        if k in v:
            out[k] = v[k]
    return out


def run_batch(command: str, patterns: list[str], pm: PluginManager,
              options: dict[str, Any] | None = None, scheduler: str | None = None,
              workers: int | None = None, bus: EventBus | None = None,
              redo: bool = False) -> list[RunOutcome]:
    """``dotshell batch COMMAND RUN_OR_GLOB ...``: re-process the study's runs on a Dask cluster
    (the scheduler at ``scheduler``, else a local cluster of ``workers`` processes); returns one
    outcome per run. ``redo`` re-processes runs this batch already finished."""
    if workers is not None and workers < 1:
        raise BatchError(f"--workers {workers}: a local cluster needs at least 1 worker "
                         "process; give a positive number or leave it out (one per core).")
    runs = find_runs(patterns)
    options = dict(options or {})
    if options.get("calibration_file"):
        options["calibration_file"] = str(Path(options["calibration_file"]).absolute())
    batch = StudyBatch(command, runs, pm, options, bus, redo)
    with dask_client(scheduler, workers) as (client, cluster):
        return batch.run(client, cluster)
