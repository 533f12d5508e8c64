"""Scan progress as people read it, folded from the event stream (pure: events in, numbers out).
The server keeps one for ``dotshell status``; each front end keeps its own, started from the
server's copy when it attaches. Times are the events' own Unix times, so a front end that
attaches in the middle of a scan (or replays its events) computes the same elapsed time and ETA
as one that watched from the start."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from dotshell.events import (Event, FrameCaptured, Message, ScanFinished, ScanPaused,
                             ScanResumed, ScanStarted, StepStarted, ViewCaptured,
                             ViewReconstructed)
from dotshell.server.describe import shown_status


@dataclass
class ScanTracker:
    """Counts of one scan and its ETA. ``status`` is ``idle`` before the first scan, then
    ``running``/``paused`` and finally the run's status (``completed``, ``aborted``,
    ``failed``). ``current_view`` is 0-based like the run directory (-1 before the first
    frame); show ``current_view + 1``."""

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
    first_frame_s: float | None = None
    finished_s: float | None = None
    paused_s: float = 0.0
    paused_before_first_frame_s: float = 0.0
    paused_since_s: float | None = None

    @property
    def frames_total(self) -> int:
        return self.n_views * self.frames_per_view

    @property
    def active(self) -> bool:
        return self.status in ("running", "paused")

    @property
    def shown_status(self) -> str:
        """The status to show: a completed scan without a single point reads ``failed``."""
        return shown_status(self.status, self.summary)

    def update(self, ev: Event, now_s: float | None = None) -> None:
        """Fold one event in; ``now_s`` (Unix seconds) defaults to the event's own time."""
        now_s = ev.time if now_s is None else now_s
        if isinstance(ev, ScanStarted):
            self.__init__()  # type: ignore[misc]  # a new scan starts from zero
            self.status, self.run_dir, self.started_s = "running", ev.run_dir, now_s
            self.n_views, self.frames_per_view = ev.n_views, ev.frames_per_view
        elif isinstance(ev, FrameCaptured):
            if self.first_frame_s is None:
                self.first_frame_s = now_s
                self.paused_before_first_frame_s = self._paused_total(now_s)
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

    def _paused_total(self, now_s: float) -> float:
        return self.paused_s + (now_s - self.paused_since_s if self.paused_since_s else 0.0)

    def active_seconds(self, now_s: float) -> float:
        """Time spent scanning so far (seconds), pauses excluded."""
        if self.started_s is None:
            return 0.0
        end = self.finished_s if self.finished_s is not None else now_s
        return max(0.0, end - self.started_s - self._paused_total(end))

    def eta_s(self, now_s: float) -> float | None:
        """Seconds left: the mean time per frame since the first frame (so the warm-up —
        connecting, calibration, flat field — does not count; moves and reconstruction
        between views do) times the frames left. None until a whole view has been captured
        (the frames of one view come in a burst: their rate, without the move and the
        reconstruction between views, promised 0:00:02 at 0:03 of a 25 s scan), after the
        last frame (the steps after the acquisition are not timed) and when not running."""
        if (not self.active or self.views_done < 1 or self.first_frame_s is None
                or self.frames_done < 2 or self.frames_done >= self.frames_total):
            return None
        paused = self._paused_total(now_s) - self.paused_before_first_frame_s
        per_frame = max(0.0, now_s - self.first_frame_s - paused) / (self.frames_done - 1)
        return per_frame * max(self.frames_total - self.frames_done, 0)

    def eta_text(self, now_s: float) -> str:
        """The ETA as people read it: ``H:MM:SS``, ``estimating`` until it has the data (a
        whole view), ``finishing`` once every frame is taken, ``--:--`` when no scan runs."""
        eta = self.eta_s(now_s)
        if eta is not None:
            return format_seconds(eta)
        if not self.active:
            return "--:--"
        return "finishing" if self.frames_total and self.frames_done >= self.frames_total \
            else "estimating"

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ScanTracker:
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in names})


def format_seconds(seconds: float | None) -> str:
    """``H:MM:SS`` (or ``--:--`` when unknown)."""
    if seconds is None:
        return "--:--"
    s = int(round(seconds))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"
