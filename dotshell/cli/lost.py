"""``dotshell lose-view RUN N [N ...] --reason TEXT`` (thin: it calls
:func:`dotshell.pipeline.lost_views.lose_views`, shows its progress and prints the report)."""

from __future__ import annotations

import argparse
from pathlib import Path

from rich.markup import escape


def cmd_lose_view(args: argparse.Namespace, pm) -> int:
    from dotshell.cli.common import ScanProgress, err, out
    from dotshell.cli.report import print_report
    from dotshell.events import EventBus
    from dotshell.pipeline.lost_views import lose_views
    from dotshell.run.store import RunStore

    bus = EventBus()
    view = ScanProgress(err)
    bus.subscribe(view)
    with view.progress:
        report = lose_views(args.run, args.views, args.reason, pm, bus)
    for lost in report.get("lost_views", []):
        out.print(f"view {lost['view']} ({lost['angle_deg']:g}°) lost: {escape(lost['reason'])}")
    status, reason = RunStore.open(Path(args.run)).status()
    print_report(report, Path(args.run))
    out.print(f"run status: [bold]{status}[/]" + (f" — {escape(reason)}" if reason else ""))
    return 0


def add_lose_view_parser(sub, pm_factory) -> None:
    """Add ``lose-view``; ``pm_factory(args)`` gives the plugin manager."""
    sp = sub.add_parser("lose-view", help="mark views whose frames are bad (and cannot be "
                        "re-captured) lost, and finish the run from the other views")
    sp.add_argument("run", help="run directory")
    sp.add_argument("views", nargs="+", type=int, metavar="N",
                    help="the view's index (the N of frames/view_NNN.tif); several may be given")
    sp.add_argument("--reason", required=True,
                    help="why the view is lost (recorded in the manifest, the event log and "
                    "the report), e.g. 'stack cut by a failed copy, sample since moved'")
    sp.set_defaults(func=lambda a: cmd_lose_view(a, pm_factory(a)))
