"""Scan progress as front ends show it, folded from the event stream (pure: events in, numbers
out; the clock is passed in so it is testable)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from dotshell.events import (Event, FrameCaptured, Message, ScanFinished, ScanPaused,
                             ScanResumed, ScanStarted, StepStarted, ViewCaptured,
                             ViewReconstructed)


@dataclass
class ScanTracker:
    """Counts of one scan and its ETA. ``status`` is ``idle`` before the first scan, then
    ``running``/``paused`` and finally the run's status (``completed``, ``aborted``,
    ``failed``)."""

    status: str = "idle"
    run_dir: str = ""
    n_views: int = 0
    frames_per_view: int = 0
    frames_done: int = 0
    views_done: int = 0
    views_reconstructed: int = 0
    points: int = 0
    step: str = ""
    current_view: int = -1
    error: str = ""
    summary: dict[str, Any] = field(default_factory=dict)
    started_s: float | None = None
    finished_s: float | None = None
    paused_s: float = 0.0
    paused_since_s: float | None = None

    @property
    def frames_total(self) -> int:
        return self.n_views * self.frames_per_view

    @property
    def active(self) -> bool:
        return self.status in ("running", "paused")

    def update(self, ev: Event, now_s: float) -> None:
        """Fold one event in; ``now_s`` is a monotonic clock reading in seconds."""
        if isinstance(ev, ScanStarted):
            self.__init__()  # type: ignore[misc]  # a new scan starts from zero
            self.status, self.run_dir, self.started_s = "running", ev.run_dir, now_s
            self.n_views, self.frames_per_view = ev.n_views, ev.frames_per_view
        elif isinstance(ev, FrameCaptured):
            self.frames_done += 1
            self.current_view = ev.view
        elif isinstance(ev, ViewCaptured):
            self.views_done += 1
        elif isinstance(ev, ViewReconstructed):
            self.views_reconstructed += 1
            self.points += ev.n_points
        elif isinstance(ev, StepStarted):
            self.step = ev.step
        elif isinstance(ev, ScanPaused):
            self.status, self.paused_since_s = "paused", now_s
        elif isinstance(ev, ScanResumed):
            self._end_pause(now_s)
            self.status = "running"
        elif isinstance(ev, Message) and ev.level == "error":
            self.error = ev.text
        elif isinstance(ev, ScanFinished):
            self._end_pause(now_s)
            self.status, self.run_dir, self.finished_s = ev.status, ev.run_dir, now_s
            self.summary = dict(ev.summary)
            self.step = ""

    def _end_pause(self, now_s: float) -> None:
        if self.paused_since_s is not None:
            self.paused_s += now_s - self.paused_since_s
            self.paused_since_s = None

    def active_seconds(self, now_s: float) -> float:
        """Time spent scanning so far, pauses excluded."""
        if self.started_s is None:
            return 0.0
        end = self.finished_s if self.finished_s is not None else now_s
        paused = self.paused_s + (now_s - self.paused_since_s if self.paused_since_s else 0.0)
        return max(0.0, end - self.started_s - paused)

    def eta_s(self, now_s: float) -> float | None:
        """Seconds left, from the mean time per frame so far (reconstruction included); None
        before the first frame or when not running."""
        if self.status not in ("running", "paused") or self.frames_done == 0:
            return None
        left = self.frames_total - self.frames_done
        return self.active_seconds(now_s) / self.frames_done * max(left, 0)


def format_seconds(seconds: float | None) -> str:
    """``H:MM:SS`` (or ``--:--`` when unknown)."""
    if seconds is None:
        return "--:--"
    s = int(round(seconds))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"
