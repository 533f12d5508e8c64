"""``dotshell batch reconstruct|mesh|normalize|validate RUN_OR_GLOB ...`` (thin: it calls
:func:`dotshell.pipeline.batch.run_batch`, shows its events and prints the study table)."""

from __future__ import annotations

import argparse
from typing import Any

from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from dotshell.cli.common import print_as_is

out = Console(highlight=False)
err = Console(stderr=True, highlight=False)


class BatchProgress:
    """Renders batch events: bars over the study's runs and tasks, one line per finished run."""

    def __init__(self, console: Console) -> None:
        self.progress = Progress(TextColumn("{task.description:<6}"), BarColumn(),
                                 MofNCompleteColumn(), TimeElapsedColumn(), console=console)
        self.runs: Any = None
        self.tasks: Any = None

    def __call__(self, ev) -> None:
        from dotshell.pipeline.batch import BatchRunFinished, BatchStarted, BatchTaskDone

        p = self.progress
        if isinstance(ev, BatchStarted):
            p.console.print(f"batch {ev.command}: {ev.runs} runs ({ev.skipped} finished "
                            f"earlier, skipped) on a {escape(ev.cluster)} ({ev.workers} "
                            "workers)")
            self.runs = p.add_task("runs", total=ev.runs, completed=ev.skipped)
            self.tasks = p.add_task("tasks", total=None)
        elif isinstance(ev, BatchTaskDone) and self.tasks is not None:
            p.update(self.tasks, completed=ev.done, total=ev.total)
        elif isinstance(ev, BatchRunFinished):
            if ev.status == "skipped":
                return
            if self.runs is not None:
                p.advance(self.runs)
            s = ev.summary
            if ev.status == "completed":
                err_pct = s.get("mean_rel_error_pct")
                p.console.print(f"  [green]completed[/] {escape(ev.run)}: {s.get('views', 0)} "
                                f"views, {s.get('points', 0)} points" +
                                ("" if err_pct is None else f", radius error {err_pct:.3f} %"),
                                soft_wrap=True)
            else:
                p.console.print(f"  [red]{ev.status}[/] {escape(ev.run)}: {escape(ev.reason)}",
                                soft_wrap=True)


def study_table(rows: list[dict[str, Any]]) -> Table:
    t = Table(title="Study")
    heads = ("run", "status", "gen", "views", "points", "mean rel. err %", "coverage %",
             "compute s", "wall s")
    for h in heads:
        t.add_column(h)
    for r in rows:
        def num(k: str, fmt: str, r: dict[str, Any] = r) -> str:
            return "" if r[k] is None else format(r[k], fmt)

        style = {"completed": "green", "skipped": "dim"}.get(r["status"], "red")
        t.add_row(escape(r["run"]), f"[{style}]{r['status']}[/]", num("generation", "03d"),
                  num("views", "d"), num("points", "d"), num("mean_rel_error_pct", ".3f"),
                  num("coverage_pct", ".1f"), num("compute_s", ".1f"), num("wall_s", ".1f"))
    return t


def cmd_batch(args: argparse.Namespace, pm) -> int:
    from dotshell.events import EventBus
    from dotshell.pipeline.batch import run_batch
    from dotshell.pipeline.batch_summary import write_study_table
    from dotshell.run.lifecycle import interrupt_reason

    options = {"calibration_file": args.calibration,
               "node_distance_mm": getattr(args, "node_distance", None),
               "normalizer": getattr(args, "normalizer", None)}
    if args.batch_command == "mesh":
        options["export"] = True
    bus = EventBus()
    view = BatchProgress(err)
    bus.subscribe(view)
    try:
        with view.progress:
            outcomes = run_batch(args.batch_command, args.runs, pm, options, args.scheduler,
                                 args.workers, bus, args.redo)
    except KeyboardInterrupt as exc:
        err.print(f"[yellow]interrupted[/]: {interrupt_reason(exc)}; runs being processed "
                  "were marked aborted and keep their published products. Run the same "
                  "command again to finish the study (finished runs are skipped).")
        return 130
    rows, csv_path, png_path = write_study_table(outcomes, args.out)
    out.print(study_table(rows))
    print_as_is(out, f"table: {csv_path}\nplot: {png_path}")
    failed = [r for r in rows if r["status"] not in ("completed", "skipped")]
    if failed:
        err.print(f"[red]{len(failed)} of {len(rows)} runs failed[/]; each run's reason is in "
                  "the table, its manifest and `dotshell inspect RUN`.")
    return 1 if failed else 0


def add_batch_parser(sub, pm_factory) -> None:
    """Add ``batch`` and its commands (those of :data:`dotshell.pipeline.batch.COMMANDS`, not
    imported here to keep the CLI's start quick); ``pm_factory(args)`` gives the plugin
    manager."""
    sp = sub.add_parser("batch", help="re-process a study (many runs) as one Dask task graph, "
                        "on a local cluster or an existing scheduler")
    bsub = sp.add_subparsers(dest="batch_command", required=True, metavar="COMMAND")
    helps = {"reconstruct": "views and everything after them (as `dotshell reconstruct`)",
             "mesh": "surface and volume meshes and exports (as `dotshell mesh`)",
             "normalize": "the trans-illumination normalization (as `dotshell normalize`)",
             "validate": "the shape validation of each run's cloud"}
    for name in helps:
        bp = bsub.add_parser(name, help=helps[name])
        bp.add_argument("runs", nargs="+", metavar="RUN_OR_GLOB",
                        help="run directories, study directories holding runs, or quoted "
                        "globs, e.g. 'study/2026*'")
        bp.add_argument("--calibration", metavar="FILE",
                        help="re-process with this calibration (checked against each run "
                        "first; re-makes the views and everything after them)")
        where = bp.add_mutually_exclusive_group()
        where.add_argument("--scheduler", metavar="ADDRESS",
                           help="an existing Dask scheduler, e.g. tcp://10.0.0.5:8786 "
                           "(default: a local cluster)")
        where.add_argument("--workers", type=int, metavar="N",
                           help="worker processes of the local cluster (default: one per core)")
        bp.add_argument("--out", default=".", help="where batch.csv and batch.png go")
        bp.add_argument("--redo", action="store_true",
                        help="also re-process runs this batch finished before")
        if name == "mesh":
            bp.add_argument("--node-distance", type=float, metavar="MM",
                            help="node distance in mm (default: each run's profile's)")
        if name == "normalize":
            bp.add_argument("--normalizer", metavar="NAME",
                            help="normalization method (default: each run's profile's)")
        bp.set_defaults(func=lambda a: cmd_batch(a, pm_factory(a)))
