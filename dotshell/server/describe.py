"""How events and paths read for people — in the TUI's log, the server's log files and
``dotshell attach``. View and frame numbers are 1-based here (``view 1`` is ``view_000`` on
disk); the data (events.jsonl, manifest.json) stays 0-based."""

from __future__ import annotations

import os
from pathlib import Path

from dotshell.events import (Event, FrameCaptured, Message, ScanFinished, ScanPaused,
                             ScanResumed, ScanStarted, StepProgress, StepStarted, ViewCaptured,
                             ViewReconstructed)

#: Log levels, least severe first.
LEVELS = ("debug", "info", "warning", "error")


def short_path(path: str | Path) -> str:
    """``path`` relative to the working directory when it lies below it."""
    p = Path(path)
    try:
        return str(p.resolve().relative_to(Path.cwd().resolve()))
    except (ValueError, OSError):
        return os.fspath(p)


def shown_status(status: str, summary: dict) -> str:
    """The status a person should read: a scan that ``completed`` without a single point
    failed in every way that matters."""
    if status == "completed" and summary.get("points", 1) == 0:
        return "failed"
    return status


def describe_event(ev: Event) -> tuple[str, str]:
    """(level, text) of an event for a log; per-frame chatter is ``debug``."""
    if isinstance(ev, Message):
        return ev.level, ev.text
    if isinstance(ev, ScanStarted):
        return "info", (f"scan started: {ev.n_views} views × {ev.frames_per_view} frames → "
                        f"{short_path(ev.run_dir)}")
    if isinstance(ev, FrameCaptured):
        return "debug", f"view {ev.view + 1} frame {ev.index + 1} ({ev.name}) captured"
    if isinstance(ev, ViewCaptured):
        return "info", (f"view {ev.view + 1} captured at {ev.angle_deg:.1f}° "
                        f"({ev.n_frames} frames)")
    if isinstance(ev, ViewReconstructed):
        quality = ("" if ev.decoded_pct is None else
                   f", {ev.decoded_pct:.1f} % of the image; {ev.reversals} neighbour reversals")
        return "info", (f"view {ev.view + 1} reconstructed: {ev.n_points} points "
                        f"({ev.decoded_pixels} decoded pixels{quality})")
    if isinstance(ev, StepStarted):
        return "info", f"step: {ev.step}"
    if isinstance(ev, StepProgress):
        return "debug", f"{ev.step}: {ev.done}/{ev.total}"
    if isinstance(ev, ScanPaused):
        return "info", f"scan paused before view {ev.view + 1}, frame {ev.index + 1}"
    if isinstance(ev, ScanResumed):
        return "info", f"scan resumed at view {ev.view + 1}, frame {ev.index + 1}"
    if isinstance(ev, ScanFinished):
        status = shown_status(ev.status, ev.summary)
        level = {"completed": "info", "aborted": "warning"}.get(status, "error")
        extra = ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}"
                          for k, v in ev.summary.items())
        why = " (no points)" if status != ev.status else ""
        if getattr(ev, "reason", ""):
            why += f" — {ev.reason}"
        return level, (f"scan {status}{why}: {short_path(ev.run_dir)}"
                       + (f" ({extra})" if extra else ""))
    kind = getattr(ev, "kind", None)
    if kind is not None and hasattr(ev, "path"):
        view = getattr(ev, "view", -1)
        where = f" (view {view + 1})" if isinstance(view, int) and view >= 0 else ""
        return "debug", f"preview {kind}{where}: {short_path(ev.path)}"
    return "debug", type(ev).__name__
