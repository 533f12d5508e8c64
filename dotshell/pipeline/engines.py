"""Acquisition engines: how the frames of a view's shots are taken, behind one protocol.

The runner (:class:`~dotshell.pipeline.acquire.Acquisition`) owns everything around a frame —
the loop over views and shots, stage moves, pause and stop, events, frame checks, writing,
integrity checks and re-captures, resume — and asks its engine for one shot's frame at a time,
in order. Two engines, chosen once per scan from the devices' capabilities and
``[scan] acquisition`` (:func:`choose_engine`):

* :class:`ShowCaptureEngine` — per frame the projector shows the pattern, the runner waits
  ``settle_ms``, the camera captures on a software call;
* :class:`~dotshell.pipeline.sequenced.SequencedCapture` — the projector runs the view's stored
  pattern sequence on its own clock and its trigger output starts each camera exposure.

An engine retries a failed device step through the runner's retry policy (``retry``) and never
writes, checks or announces a frame.
"""

from __future__ import annotations

import time
from typing import Any, Callable, Mapping, Protocol, Sequence, TypeVar

import numpy as np

from dotshell.coding import PatternFrame
from dotshell.devices import FrameInfo, FrameInfoSource, accepted_kwargs, implements
from dotshell.errors import DeviceError
from dotshell.events import EventBus
from dotshell.pipeline.pdi import Shot
from dotshell.pipeline.sequenced import SequencedCapture, uses_sequenced

T = TypeVar("T")

#: ``retry(action, what)``: ``action()`` under the scan's retry policy, ``what`` naming the step
#: in warnings and in the final error (:func:`dotshell.pipeline.acquire.with_retries`).
Retry = Callable[[Callable[[], T], str], T]


class AcquisitionEngine(Protocol):
    """Takes the frames of a view's shots; the runner asks for shot 0, 1, ... of each view."""

    #: the ``[scan] acquisition`` mode this engine is: "show-capture" or "sequenced"
    name: str

    def frame(self, view: int, index: int) -> tuple[np.ndarray, FrameInfo | None]:
        """The raw frame of shot ``index`` of ``view`` and its metadata (None when the camera
        gives none); a DeviceError once the retries are spent."""
        ...

    def holds_frames(self) -> bool:
        """Whether frames already captured wait to be handed over: a stop must not drop them."""
        ...


class AnalyzerAngle:
    """The rig's analyzer as last set (degrees, None = unknown): turned only when a shot needs
    another angle, and set again after a failed step."""

    def __init__(self, rig: Any) -> None:
        self.rig = rig
        self.degrees: float | None = None

    def turn_to(self, degrees: float) -> None:
        if degrees != self.degrees:
            self.degrees = None  # unknown until the move succeeds
            self.rig.analyzer.set_angle(degrees)
            self.degrees = degrees

    def forget(self) -> None:
        self.degrees = None


class ShowCaptureEngine:
    """Per frame: turn the analyzer if the shot needs it, show the pattern, wait ``settle_ms``
    (the projector's display latency), capture; retried as one step."""

    name = "show-capture"

    def __init__(self, rig: Any, patterns: Sequence[PatternFrame], shots: Sequence[Shot],
                 settle_ms: float, analyzer: AnalyzerAngle, retry: Retry) -> None:
        self.rig = rig
        self.patterns = patterns
        self.shots = list(shots)
        self.settle_ms = float(settle_ms)
        self.analyzer = analyzer
        self.retry = retry
        self._show_kwargs = accepted_kwargs(rig.projector.show, ("name", "index"))
        self._frame_info = implements(rig.camera, FrameInfoSource)

    def holds_frames(self) -> bool:
        return False

    def frame(self, view: int, index: int) -> tuple[np.ndarray, FrameInfo | None]:
        shot = self.shots[index]
        image = self.retry(lambda: self._show_and_capture(shot, index),
                           f"view {view}, frame {shot.name!r}")
        return image, self.rig.camera.last_frame_info() if self._frame_info else None

    def _show_and_capture(self, shot: Shot, index: int) -> np.ndarray:
        pattern = self.patterns[shot.pattern]
        try:
            if shot.analyzer_deg is not None:
                self.analyzer.turn_to(shot.analyzer_deg)
            ident = {"name": pattern.name, "index": shot.pattern}
            self.rig.projector.show(pattern.image, **{k: ident[k] for k in self._show_kwargs})
            if self.settle_ms > 0:
                time.sleep(self.settle_ms / 1000.0)
            return self.rig.camera.capture()
        except DeviceError:
            self.analyzer.forget()  # unknown after a failure: set it again
            raise


def choose_engine(rig: Any, patterns: Sequence[PatternFrame], shots: Sequence[Shot],
                  scan: Mapping[str, Any], bus: EventBus, retry: Retry) -> AcquisitionEngine:
    """The engine for a scan with ``scan`` settings on ``rig``: sequenced when the projector
    stores sequences and the camera takes a trigger (and ``acquisition`` allows it), else
    show-capture; a ProfileError when ``acquisition = "sequenced"`` is asked of devices that
    cannot (:func:`~dotshell.pipeline.sequenced.uses_sequenced`)."""
    analyzer = AnalyzerAngle(rig)
    if uses_sequenced(rig, scan):
        return SequencedCapture(rig, patterns, shots, scan, bus, retry, analyzer.turn_to)
    return ShowCaptureEngine(rig, patterns, shots, scan["settle_ms"], analyzer, retry)
