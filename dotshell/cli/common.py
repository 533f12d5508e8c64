"""What the commands share: printing (``out``, ``err``), the scan progress view, and the
plugin manager from the command line's options."""

from __future__ import annotations

import argparse
import time
from typing import TYPE_CHECKING, Any

from rich.console import Console
from rich.markup import escape
from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn,
                           TimeElapsedColumn, TimeRemainingColumn)

from dotshell.events import (FrameCaptured, Message, ScanStarted, StepStarted, ViewCaptured,
                             ViewReconstructed)

if TYPE_CHECKING:
    from dotshell.plugins import PluginManager

err = Console(stderr=True, highlight=False)
out = Console(highlight=False)


def plugin_manager(args: argparse.Namespace) -> PluginManager:
    """The plugin manager (``--strict-plugins`` from ``args``); load errors printed as warnings."""
    from dotshell.plugins import get_plugin_manager

    pm = get_plugin_manager(strict=args.strict_plugins)
    for e in pm.load_errors:
        err.print(f"[yellow]warning:[/] {escape(str(e))}")
    return pm


class StallAwareRemaining(TimeRemainingColumn):
    """The ETA, or ``stalled N s`` when a task has not advanced for ``STALL_S`` seconds (a device
    or a step that hangs is shown as such, not as an ETA of one second)."""

    STALL_S = 30.0

    def __init__(self, last_advance: dict[Any, float]) -> None:
        super().__init__()
        self.last_advance = last_advance

    def render(self, task):
        from rich.text import Text

        last = self.last_advance.get(task.id)
        if last is not None and not task.finished:
            idle = time.monotonic() - last
            if idle > self.STALL_S:
                return Text(f"stalled {idle:.0f} s", style="bold yellow")
        return super().render(task)


class ScanProgress:
    """Renders scan events as progress bars (views, frames, ETA) and log lines."""

    def __init__(self, console: Console) -> None:
        self.last_advance: dict[Any, float] = {}
        self.progress = Progress(TextColumn("{task.description:<12}"), BarColumn(),
                                 MofNCompleteColumn(), TimeElapsedColumn(), TextColumn("ETA"),
                                 StallAwareRemaining(self.last_advance), console=console,
                                 transient=False)
        self.tasks: dict[str, Any] = {}
        self.console = console
        #: the view problems whose meaning and fix were printed (once per command)
        self.noted: set[str] = set()

    def __call__(self, ev) -> None:
        p = self.progress
        if isinstance(ev, ScanStarted):
            self.tasks["views"] = p.add_task("views", total=ev.n_views)
            self.tasks["frames"] = p.add_task("frames", total=ev.n_views * ev.frames_per_view)
            for t in self.tasks.values():
                self.last_advance[t] = time.monotonic()
        elif isinstance(ev, FrameCaptured) and "frames" in self.tasks:
            p.advance(self.tasks["frames"])
            self.last_advance[self.tasks["frames"]] = time.monotonic()
        elif isinstance(ev, ViewCaptured) and "views" in self.tasks:
            p.advance(self.tasks["views"])
            self.last_advance[self.tasks["views"]] = time.monotonic()
        elif isinstance(ev, ViewReconstructed):
            self.view_line(ev)
        elif isinstance(ev, StepStarted) and ev.step not in ("acquire",):
            p.console.print(f"[dim]→ {ev.step}[/]")
        elif isinstance(ev, Message):
            style = {"warning": "yellow", "error": "red"}.get(ev.level, "dim")
            p.console.print(f"[{style}]{ev.level}:[/] {escape(ev.text)}")

    def view_line(self, ev: ViewReconstructed) -> None:
        """``  view   3:    51234 points; decoded 38.1 % of the image, 12 neighbour reversals
        (0.03 % of decoded); uncertain 27.0 %`` and, the first time this command meets a
        problem, what it means and what would fix it
        (:func:`dotshell.pipeline.decode_quality.view_notes`)."""
        line = f"  view {ev.view + 1:3d}: {ev.n_points:8d} points"
        if ev.decoded_pct is not None:
            line += (f"; decoded {ev.decoded_pct:.1f} % of the image, {ev.reversals} neighbour "
                     f"reversals ({ev.reversals_pct:.2f} % of decoded)")
        notes = [(str(k), float(pct)) for k, pct in ev.notes]
        losses = [f"{k.replace('_', ' ')} {pct:.1f} %" for k, pct in notes if k != "reversals"]
        if losses:
            line += "; " + ", ".join(losses)
        print_as_is(self.console, line)
        from dotshell.pipeline.reconstruct import note_text

        for key, pct in notes:
            if key not in self.noted:
                self.noted.add(key)
                print_as_is(self.console, f"    {note_text(key, pct)}")


def print_as_is(console: Console, text: str) -> None:
    """Print ``text`` as it is: no rich markup read from it (a path or name may hold ``[...]``)
    and no line break put inside it where the output is narrow (a pipe is 80 columns), so a
    path printed is a path a user or a script can copy."""
    console.print(text, markup=False, soft_wrap=True)
