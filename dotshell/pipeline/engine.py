"""The workflow engine: one owner of a run's lifecycle, and the steps a job needs for its targets.

A **job** is one command working on one run (``scan``, ``resume``, ``reconstruct``, ``mesh``,
``normalize``, ``forward``, a batch task). :class:`RunJob` holds the run's lock for the job,
records ``status = running`` and, when the job ends, its outcome — ``completed``, ``failed``
(with the reason), ``aborted`` (with the signal or the user) — in the manifest's ``jobs``
history. The run's ``status`` is then what is true of the run: a scan's or resume's outcome;
after a re-processing job the state it had before (a failed re-processing publishes nothing),
except that a successful one makes a fully captured run ``completed``. :func:`process` runs the steps of
:mod:`dotshell.pipeline.steps` that the targets need into a new generation and publishes it
(:mod:`dotshell.run.generations`); products the job does not change are carried over,
products that would be stale are dropped, so a published generation is always consistent.
:func:`process` is three parts that may run in different processes: :func:`prepare` (plan and
carry over, under the job's lock), :func:`run_steps` (the steps, e.g. on a batch's workers, which
need no lock: only the job writes its generation) and :func:`publish` (by the job's process).
"""

from __future__ import annotations

import os
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

from dotshell import __version__
from dotshell.errors import DotshellError, RunError
from dotshell.events import EventBus, StepStarted
from dotshell.run.generations import (Generation, ProductStore, current_number,
                                           published, remove_unpublished)
from dotshell.run.layout import RunLayout
from dotshell.run.lifecycle import Interrupted, RunLock, effective_status
from dotshell.run.lost import finished, lost_reason
from dotshell.pipeline.kernel_warmup import kernels_before_views
from dotshell.pipeline.steps import STEP_BY_NAME, STEPS, StepContext, import_ahead
from dotshell.plugins import PluginManager
from dotshell.profile.loader import Profile
from dotshell.run.store import FULL, RESERVE_BYTES, RunStore


class RunJob:
    """Context manager: the lifecycle of one job on one run (see the module docstring)."""

    def __init__(self, store: RunStore, command: str, bus: EventBus | None = None,
                 create: Callable[[], None] | None = None, batch: str | None = None) -> None:
        """``create``: writes a new run's first files (profile, manifest) once the lock is
        held, so no other process ever sees a new run without its writer. ``batch``: the key
        of the study batch this job belongs to, recorded with the job (``dotshell batch``
        skips runs whose history holds it completed)."""
        self.create = create
        self.batch = batch
        self.store = store
        self.command = command
        self.bus = bus or EventBus()
        self.lock = RunLock(store.root)
        self.status: str | None = None
        self.reason = ""
        self.generation: int | None = None
        self.previous: tuple[str, str] = ("unknown", "")
        self.started = 0.0

    def __enter__(self) -> RunJob:
        return self.open()

    def __exit__(self, exc_type: Any, exc: BaseException | None, tb: Any) -> None:
        self.close(exc)

    def open(self) -> RunJob:
        """Take the run's lock and record ``running`` (what ``with RunJob(...)`` does first)."""
        self.lock.acquire(self.command)
        try:
            if self.create is not None:
                self.create()
            manifest = self.store.manifest
            self.previous = effective_status(self.store.root, manifest)
            if self.create is None and manifest["status"] == "running":  # its writer is gone
                self._history({"command": (manifest.get("job") or {}).get("command", "?"),
                               "status": "interrupted", "reason": self.previous[1]})
            full = self.store.reserve_space()
            if full is not None and full.errno in FULL and self.create is None:
                # nothing written yet: the run keeps its true status instead of a 'running'
                # the full disk would not let this job take back
                raise RunError(f"{self.store.root}: the disk is full ({full.strerror}): there is "
                               f"not even room for the {RESERVE_BYTES // 1024} kB the job holds "
                               "back to record its outcome. Free disk space and run the "
                               "command again; the run is unchanged.")
            for p in [*self.store.clean_orphans(), *remove_unpublished(self.store.root)]:
                self.bus.info(f"removed {p.relative_to(self.store.root)}, left by an "
                              "interrupted job")
            self.started = time.time()
            self.store.update_manifest(status="running", reason="", job={
                "command": self.command, "pid": os.getpid(), "host": socket.gethostname(),
                "started": time.strftime("%Y-%m-%dT%H:%M:%S"), "dotshell": __version__,
                **self._batch_entry()})
        except BaseException:
            self.store.release_reserve()
            self.lock.release()
            raise
        return self

    def finish(self, status: str, reason: str = "") -> None:
        """Decide the job's final state (recorded when the job's block ends)."""
        self.status, self.reason = status, reason

    def close(self, exc: BaseException | None = None) -> None:
        """Record the job's outcome (``exc``: what ended it, if anything) and release the
        lock (what the end of a ``with RunJob(...)`` block does)."""
        try:
            if exc is not None:
                self.status, self.reason = outcome_of(exc)
            elif self.status is None:
                self.status = "completed"
            if self.status != "completed" and not self.captures:
                cur = current_number(self.store.root)
                if cur is not None and cur == self.generation:  # stopped after publishing
                    self.reason += f" (after its generation {cur} was published)"
                elif cur is not None:
                    self.reason += (f" (nothing published: generation {cur} is unchanged and "
                                    "still the run's products)")
            if self.generation is not None and not published(self.store.root, self.generation):
                remove_unpublished(self.store.root, only=self.generation)
                self.generation = None
            self._history({"command": self.command, "status": self.status,
                           "reason": self.reason, "generation": self.generation,
                           **self._batch_entry()}, **self.run_state(), job=None)
        finally:
            self.store.release_reserve()
            self.lock.release()

    @property
    def captures(self) -> bool:
        """Whether this job captures (scan, resume) rather than re-processes."""
        return self.command in ("scan", "resume")

    def run_state(self) -> dict[str, str]:
        """The run's status after this job: a capturing job's own outcome; after a
        re-processing job the run keeps its state, except that a successful one makes a run
        whose every view is captured (or marked lost) ``completed`` (its products are now
        whole). A completed run with lost views says so in its reason."""
        manifest = self.store.manifest
        if self.captures:
            status, reason = self.status or "failed", self.reason
        else:
            status, reason = self.previous
            if self.status == "completed" and all(finished(v) for v in manifest["views"]):
                status, reason = "completed", ""
        if status == "completed":
            reason = reason or lost_reason(manifest)
        return {"status": status, "reason": reason}

    def _batch_entry(self) -> dict[str, str]:
        return {"batch": self.batch} if self.batch else {}

    def _history(self, entry: dict[str, Any], **changes: Any) -> None:
        """Append ``entry`` to the manifest's ``jobs``, with ``changes`` in the same write (a
        kill never leaves a job recorded without the run state it implies)."""
        m = self.store.manifest
        entry = {**entry, "finished": time.strftime("%Y-%m-%dT%H:%M:%S")}
        if self.started:
            entry["seconds"] = round(time.time() - self.started, 3)
        self.store.update_manifest(jobs=[*m.get("jobs", []), entry], **changes)


def outcome_of(exc: BaseException) -> tuple[str, str]:
    """(status, reason) for a job that ended with ``exc``."""
    if isinstance(exc, Interrupted):
        return "aborted", exc.reason
    if isinstance(exc, KeyboardInterrupt):
        return "aborted", "stopped by Ctrl-C (SIGINT)"
    if isinstance(exc, DotshellError):
        return "failed", str(exc)
    if isinstance(exc, MemoryError):
        return "failed", "out of memory"
    return "failed", f"{type(exc).__name__}: {exc}"


# ---- planning and running steps ----------------------------------------------------------------

def plan(targets: Iterable[str], ctx: StepContext, base: set[str]) -> tuple[list[str], list[str],
                                                                            list[str]]:
    """(steps to run, products to carry over, products dropped as stale), in step order.

    A step runs when it is a target, when a target needs its product and the base generation
    lacks it, or when something it reads runs and the run wants it (the profile asks for it,
    or the base has it); a product of the base is carried over when nothing it reads runs, and
    dropped as stale otherwise."""
    targets = set(targets)
    unknown = targets - {s.name for s in STEPS}
    if unknown:
        raise RunError(f"unknown products {sorted(unknown)}; known: {[s.name for s in STEPS]}")
    needed = set(targets)
    for step in reversed(STEPS):  # what the targets read, transitively, unless in the base
        if step.name in targets or (step.name in needed and step.name not in base):
            needed.update(step.reads)
    run: list[str] = []
    carry: list[str] = []
    dropped: list[str] = []
    for step in STEPS:
        upstream_runs = any(r in run for r in step.reads)
        wanted = step.name in needed or step.wanted(ctx, base)
        if step.name in targets or (step.name in needed and step.name not in base) or (
                upstream_runs and wanted):
            run.append(step.name)
        elif step.name in base and not upstream_runs:
            carry.append(step.name)
        elif step.name in base:
            dropped.append(step.name)
    return run, carry, dropped


@dataclass
class JobWork:
    """A job's planned work, ready to run wherever the run directory is visible (a batch worker
    as well as the job's own process): the run, the generation being written, the steps to run
    in order, the command's options, and the report and product files carried over from the
    base generation. Small and picklable; :func:`prepare` makes it under the run's lock,
    :func:`run_steps` executes (some of) its steps, :func:`publish` publishes the result."""

    run_root: Path
    generation: int
    base: int | None
    steps: list[str]
    dropped: list[str]
    options: dict[str, Any]
    report: dict[str, Any]
    files: dict[str, list[str]]
    timings: dict[str, float]

    def generation_of(self, run: RunStore) -> Generation:
        return Generation(run, self.generation, self.base)


@dataclass
class StepsDone:
    """What :func:`run_steps` made: report sections, product files and step seconds."""

    report: dict[str, Any] = field(default_factory=dict)
    files: dict[str, list[str]] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)


def prepare(job: RunJob, profile: Profile, pm: PluginManager, targets: Iterable[str],
            options: dict[str, Any] | None = None,
            generation: Generation | None = None) -> JobWork:
    """Start ``job``'s generation (``generation``: one the caller already writes into, as a
    scan does), plan the steps ``targets`` need and carry the unchanged products over.
    Runs in the process that holds the run's lock."""
    gen = generation or Generation.start(job.store)
    job.generation = gen.number
    if gen.missing_base is not None:
        job.bus.warn(f"{job.store.root}/{RunLayout.CURRENT} points to "
                     f"{RunLayout.generation_dir(gen.missing_base)}, which is "
                     f"missing (deleted?); generation {gen.number} makes every product again "
                     "from the frames.")
    options = dict(options or {})
    ctx = StepContext(ProductStore(job.store, gen.dir), profile, pm, job.bus, options,
                      before_views=kernels_before_views)
    base = set(gen.base_products())
    run, carry, dropped = plan(targets, ctx, base)
    gen.carry(carry)
    base_report = gen.base_report()
    report: dict[str, Any] = {"profile": profile.name, "generation": gen.number,
                              "based_on": gen.base, "command": job.command}
    for name in REPORT_ONLY:  # generations published before report-only products were listed
        if (name not in base and name not in run and any(k in base_report for k in sections_of(name))
                and not any(r in run for r in STEP_BY_NAME[name].reads)):
            carry.append(name)
    for name in carry:
        gen.files.setdefault(name, [])
        report.update({k: base_report[k] for k in sections_of(name) if k in base_report})
    timings = dict(base_report.get("timings_s", {})) if carry else {}
    return JobWork(job.store.root, gen.number, gen.base, run, dropped, options, report,
                   dict(gen.files), timings)


def run_steps(work: JobWork, profile: Profile, pm: PluginManager, bus: EventBus,
              names: Iterable[str] | None = None,
              extra: dict[str, Any] | None = None) -> StepsDone:
    """Run ``names`` (default: all of ``work.steps``, in that order) into the job's generation.
    Needs no lock: only the job writes its generation. ``extra`` adds options for these steps:
    ``reconstructed`` (view → record of views already made), ``prewritten`` (product → files
    already in the generation that belong to it), ``timings`` (seconds already measured)."""
    names = list(work.steps if names is None else names)
    run = RunStore(work.run_root)
    gen = work.generation_of(run)
    gen.files = {p: list(f) for p, f in work.files.items()}
    options = {**work.options, **(extra or {})}
    ctx = StepContext(ProductStore(run, gen.dir), profile, pm, bus, options,
                      before_views=kernels_before_views)
    ctx.timings.update(options.pop("timings", {}))
    prewritten: dict[str, set[str]] = options.pop("prewritten", {})
    done = StepsDone()
    for name in names:
        import_ahead(names, name)
        before = gen.listing() - prewritten.get(name, set())
        t0 = time.perf_counter()
        try:
            done.report.update(STEP_BY_NAME[name].run(ctx))
        except OSError as exc:
            if exc.filename is None:  # a library's write (a mesh, an export) names no file:
                exc.filename = f"{gen.dir}/ (step {name})"  # the step writes only there
            raise
        ctx.timings.setdefault(_timing_name(name), time.perf_counter() - t0)
        gen.record(name, before)
        # a product may be report sections only (validation): listed without files, it is
        # carried into later generations like any other, never lost without a word
        done.files[name] = gen.files.setdefault(name, [])
    done.timings = dict(ctx.timings)
    return done


def publish(job: RunJob, work: JobWork, done: Iterable[StepsDone],
            final_status: str = "completed") -> dict[str, Any]:
    """Publish ``work``'s generation with what its steps made (``done``, in step order);
    returns the report. Only the job holding the run's lock publishes."""
    if not job.lock.held or job.store.root != work.run_root:
        raise RunError(f"{work.run_root}: generation {work.generation} can only be published "
                       "by the job that holds the run's lock.")
    gen = work.generation_of(job.store)
    gen.files = {p: list(f) for p, f in work.files.items()}
    report = dict(work.report)
    timings = dict(work.timings)
    for part in done:
        report.update(part.report)
        gen.files.update(part.files)
        timings.update({k: round(s, 3) for k, s in part.timings.items()})
    report["timings_s"] = timings
    if work.dropped:
        report["dropped"] = work.dropped
        job.bus.warn(f"generation {gen.number}: {', '.join(work.dropped)} of generation "
                     f"{gen.base} would be stale after this change and were left out; re-make "
                     "them if needed (e.g. `dotshell mesh RUN`).")
    report["status"] = final_status
    if not job.captures:
        report["reprocessed"] = True
    job.bus.emit(StepStarted(step="publish"))
    gen.report = report
    gen.publish()
    return report


def process(job: RunJob, profile: Profile, pm: PluginManager, targets: Iterable[str],
            options: dict[str, Any] | None = None, final_status: str = "completed",
            generation: Generation | None = None) -> dict[str, Any]:
    """Make ``targets`` (and whatever they need) in a new generation of ``job``'s run and
    publish it, all in this process; returns the published report. ``generation``: one the
    caller already started writing into (a scan writes views while it captures). Options
    ``reconstructed``, ``prewritten`` and ``timings`` are as in :func:`run_steps`; option
    ``calibration`` is the generation's calibration the caller already loaded and checked (a
    :class:`RigCalibration`, so that the file is read once)."""
    options = dict(options or {})
    extra: dict[str, Any] = {k: options.pop(k) for k in ("reconstructed", "prewritten", "timings",
                                                               "calibration")
                             if k in options}
    work = prepare(job, profile, pm, targets, options, generation)
    return publish(job, work, [run_steps(work, profile, pm, job.bus, extra=extra)],
                   final_status)


#: Products made of report.json sections only, without files.
REPORT_ONLY = ("validation",)


def sections_of(product: str) -> tuple[str, ...]:
    """The report.json sections a product's step writes."""
    return {"calibration": ("calibration",), "views": ("views", "lost_views"), "cloud": ("cloud",),
            "validation": ("validation",), "previews": ("previews",), "mesh": ("mesh",),
            "normalize": ("normalize",), "exports": ("exports",),
            "forward": ("forward",)}.get(product, ())


def _timing_name(step: str) -> str:
    return {"views": "reconstruct", "cloud": "merge", "validation": "validate",
            "exports": "export"}.get(step, step)
