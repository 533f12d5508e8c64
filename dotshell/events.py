"""Workflow events and the bus that front ends (CLI, TUI, console) and the run log subscribe to.

Events are small frozen dataclasses; ``to_dict()`` gives the JSON line written to
``events.jsonl`` (with ``"event"`` = the class name and ``"time"`` = Unix seconds).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from typing import Any, Callable

from dotshell.errors import DotshellError


@dataclass(frozen=True)
class Event:
    time: float = field(default_factory=time.time, kw_only=True)

    def to_dict(self) -> dict[str, Any]:
        return {"event": type(self).__name__, **asdict(self)}


@dataclass(frozen=True)
class ScanStarted(Event):
    run_dir: str
    profile: str
    n_views: int
    frames_per_view: int


@dataclass(frozen=True)
class FrameCaptured(Event):
    view: int
    index: int
    name: str


@dataclass(frozen=True)
class ViewCaptured(Event):
    view: int
    angle_deg: float
    n_frames: int


@dataclass(frozen=True)
class ScanPaused(Event):
    """The acquisition is waiting before frame ``index`` of ``view`` (everything before it is
    on disk) until it is resumed or stopped."""

    view: int
    index: int


@dataclass(frozen=True)
class ScanResumed(Event):
    view: int
    index: int


@dataclass(frozen=True)
class StepStarted(Event):
    """A pipeline step began: acquire, decode, triangulate, merge, validate, previews."""

    step: str
    total: int = 0


@dataclass(frozen=True)
class StepProgress(Event):
    step: str
    done: int
    total: int


@dataclass(frozen=True)
class ViewReconstructed(Event):
    """A view decoded and triangulated. ``decoded_pct`` (% of the image), ``reversals`` and
    ``reversals_pct`` (% of the decoded pixels): its decode quality
    (:mod:`dotshell.pipeline.decode_quality`); ``notes``: the losses and quality problems worth
    their meaning and fix, (key, share %) as
    :func:`dotshell.pipeline.decode_quality.view_notes` gives them."""

    view: int
    n_points: int
    decoded_pixels: int
    decoded_pct: float | None = None
    reversals: int | None = None
    reversals_pct: float | None = None
    notes: tuple[tuple[str, float], ...] = ()


@dataclass(frozen=True)
class Message(Event):
    """A log line: level is ``info``, ``warning`` or ``error``."""

    level: str
    text: str


@dataclass(frozen=True)
class ScanFinished(Event):
    """A scan (or its resume) ended: ``status`` is ``completed``, ``aborted`` or ``failed``;
    ``reason`` says why when it is not ``completed``."""

    status: str
    run_dir: str
    summary: dict[str, Any] = field(default_factory=dict)
    reason: str = ""


Subscriber = Callable[[Event], None]


class EventBus:
    """Synchronous publish/subscribe. A subscriber that raises is dropped from that event only;
    the error is re-published as a warning ``Message`` so it is never silent."""

    def __init__(self) -> None:
        self._subs: list[Subscriber] = []

    def subscribe(self, fn: Subscriber) -> Callable[[], None]:
        self._subs.append(fn)
        return lambda: self._subs.remove(fn) if fn in self._subs else None

    def emit(self, event: Event) -> None:
        for fn in list(self._subs):
            try:
                fn(event)
            except Exception as exc:
                if isinstance(event, Message) and event.level == "warning":
                    continue  # avoid loops
                text = str(exc) if isinstance(exc, DotshellError) else (
                    f"event subscriber {fn!r} failed: {type(exc).__name__}: {exc}")
                self.emit(Message(level="warning", text=text))

    def info(self, text: str) -> None:
        self.emit(Message(level="info", text=text))

    def warn(self, text: str) -> None:
        self.emit(Message(level="warning", text=text))
