"""How session state reads on screen: paths, device status, event log lines (pure strings)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

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


def describe_status(role: str, status: dict[str, Any], projected: str | None = None,
                    compact: bool = False) -> str:
    """One line of a device's live status: angle, exposure, pattern, ... ; errors first.
    ``compact`` keeps only angle, exposure, pattern and on/off."""
    if "error" in status:
        return f"error: {status['error']}"
    parts = []
    if "angle_deg" in status:
        parts.append(f"angle {float(status['angle_deg']):.2f}°")
    if "exposure_ms" in status:
        parts.append(f"exposure {float(status['exposure_ms']):g} ms")
    if role == "projector" and projected:
        parts.append(f"pattern {projected}")
    if "on" in status:
        parts.append("on" if status["on"] else "off")
    shown = {"angle_deg", "exposure_ms", "on", "connected", "simulated"}
    for key, value in ([] if compact else status.items()):
        if key not in shown:
            if isinstance(value, (list, tuple)):
                value = "×".join(map(str, value))
            parts.append(f"{key.replace('_', ' ')} {value}")
    return " · ".join(parts)


def describe_event(ev: Event) -> tuple[str, str]:
    """(level, text) of an event for the log; per-frame chatter is ``debug``."""
    if isinstance(ev, Message):
        return ev.level, ev.text
    if isinstance(ev, ScanStarted):
        return "info", (f"scan started: {ev.n_views} views × {ev.frames_per_view} frames → "
                        f"{short_path(ev.run_dir)}")
    if isinstance(ev, FrameCaptured):
        return "debug", f"view {ev.view} frame {ev.index} ({ev.name}) captured"
    if isinstance(ev, ViewCaptured):
        return "info", f"view {ev.view} captured at {ev.angle_deg:.1f}° ({ev.n_frames} frames)"
    if isinstance(ev, ViewReconstructed):
        return "info", (f"view {ev.view} reconstructed: {ev.n_points} points "
                        f"({ev.decoded_pixels} decoded pixels)")
    if isinstance(ev, StepStarted):
        return "info", f"step: {ev.step}"
    if isinstance(ev, StepProgress):
        return "debug", f"{ev.step}: {ev.done}/{ev.total}"
    if isinstance(ev, ScanPaused):
        return "info", f"scan paused before view {ev.view}, frame {ev.index}"
    if isinstance(ev, ScanResumed):
        return "info", f"scan resumed at view {ev.view}, frame {ev.index}"
    if isinstance(ev, ScanFinished):
        level = {"completed": "info", "aborted": "warning"}.get(ev.status, "error")
        extra = ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}"
                          for k, v in ev.summary.items())
        return level, (f"scan {ev.status}: {short_path(ev.run_dir)}"
                       + (f" ({extra})" if extra else ""))
    kind = getattr(ev, "kind", None)
    if kind is not None and hasattr(ev, "path"):
        return "debug", f"preview {kind}: {short_path(ev.path)}"
    return "debug", type(ev).__name__
