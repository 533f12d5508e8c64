"""The simulator's time model: a clock, the projector's display timeline and its trigger output.

Real rigs lose their time to waiting: for the projector to put a new image on its panel
(display latency), for the camera to expose and read out a frame. The simulator renders a frame
in a few milliseconds to a second, which says nothing about either. So the simulated devices
keep their own clock:

* :class:`SimClock` runs with the host's wall clock (the runner's ``settle_ms`` sleeps, its
  bookkeeping and disk writes all count), **minus** the simulator's own computing time (ray
  casting is the photons' job, free on a real rig), **plus** the waits the modelled hardware
  would take (exposure, readout, a sequence running): those are added to the clock instead of
  slept, so tests stay fast while the clock reads what a real rig's would.
* :class:`DisplayTimeline` records what the projector's panel shows when: a pattern passed to
  ``show()`` appears ``display_latency_ms`` later (at the next refresh when ``refresh_hz`` is
  set); a hardware sequence puts each pattern up for its exposure, then dark until the next
  period, with a trigger edge at the start of each pattern.
* A camera exposure over ``[t0, t1]`` integrates what the panel showed in that window
  (:meth:`DisplayTimeline.weights`): a capture taken before the pattern settled sees a blend
  of the old and new pattern, as a real camera would.

With every time setting at its default of 0 the panel changes the instant ``show()`` is
called and frames are identical to a simulator without a time model.

Units: clock times in seconds (``*_s``), settings in milliseconds (``*_ms``).
"""

from __future__ import annotations

import math
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Iterator

import numpy as np


class SimClock:
    """Simulated time of one rig, in seconds since the clock was made."""

    def __init__(self) -> None:
        self._origin = time.perf_counter()
        self._offset = 0.0  # + modelled waits − simulator computing time
        self._lock = threading.Lock()

    def now(self) -> float:
        with self._lock:
            return time.perf_counter() - self._origin + self._offset

    def advance(self, seconds: float) -> None:
        """Let ``seconds`` of modelled hardware time pass (without sleeping)."""
        if seconds > 0:
            with self._lock:
                self._offset += seconds

    def advance_to(self, t_s: float) -> None:
        """Let time pass until ``t_s`` (no-op if it is already later)."""
        self.advance(t_s - self.now())

    @contextmanager
    def computing(self) -> Iterator[None]:
        """A block of simulator computation that takes no time on a real rig."""
        t0 = time.perf_counter()
        try:
            yield
        finally:
            with self._lock:
                self._offset -= time.perf_counter() - t0


@dataclass(frozen=True)
class Segment:
    """The panel shows ``image`` (uint8 (h, w); ``None`` = dark, LEDs off) from ``start_s``
    until the next segment starts."""

    start_s: float
    image: np.ndarray | None
    name: str = ""
    index: int = -1


class DisplayTimeline:
    """What the projector's panel shows over time, and the trigger edges it sends."""

    #: Segments kept before the newest (enough for any exposure window still to be taken).
    KEEP = 8

    def __init__(self) -> None:
        self.segments: list[Segment] = [Segment(-math.inf, None)]
        self.triggers_s: list[float] = []

    def show(self, at_s: float, image: np.ndarray | None, name: str = "",
             index: int = -1) -> None:
        """From ``at_s`` on the panel shows ``image``; later segments are replaced."""
        kept = [s for s in self.segments if s.start_s < at_s]
        self.segments = (kept[-self.KEEP:] or [Segment(-math.inf, None)]) + [
            Segment(at_s, image, name, index)]

    def run_sequence(self, start_s: float, images: list[tuple[np.ndarray, str, int]],
                     exposure_s: float, period_s: float) -> None:
        """Pattern k is lit over ``[start + k·period, start + k·period + exposure)``, dark for
        the rest of its period; a trigger edge at the start of each pattern; dark after."""
        self.show(start_s, None)
        self.segments.pop()  # replaced by the sequence below
        for k, (image, name, index) in enumerate(images):
            t = start_s + k * period_s
            self.segments.append(Segment(t, image, name, index))
            if exposure_s < period_s:
                self.segments.append(Segment(t + exposure_s, None))
        self.segments.append(Segment(start_s + len(images) * period_s, None))
        self.triggers_s = [start_s + k * period_s for k in range(len(images))]

    def stop(self, at_s: float) -> None:
        """Stop a running sequence: dark from ``at_s``; edges after it never come."""
        self.show(at_s, None)
        self.triggers_s = [t for t in self.triggers_s if t < at_s]

    def weights(self, t0_s: float, t1_s: float) -> list[tuple[float, Segment]]:
        """The segments the panel showed during ``[t0, t1)`` with the share of the window each
        covered (shares sum to 1). An empty window counts the segment at ``t0``."""
        if t1_s <= t0_s:
            seg = next(s for s in reversed(self.segments) if s.start_s <= t0_s)
            return [(1.0, seg)]
        out = []
        for seg, nxt in zip(self.segments, self.segments[1:] + [Segment(math.inf, None)]):
            lo, hi = max(seg.start_s, t0_s), min(nxt.start_s, t1_s)
            if hi > lo:
                out.append(((hi - lo) / (t1_s - t0_s), seg))
        return out


def display_time(show_s: float, latency_ms: float, refresh_hz: float) -> float:
    """When a frame handed to the display at ``show_s`` is on the panel: after the display
    latency, at the next refresh boundary when the display refreshes at ``refresh_hz``."""
    t = show_s + latency_ms / 1000.0
    if refresh_hz > 0:
        frame = 1.0 / refresh_hz
        t = math.ceil(t / frame - 1e-9) * frame
    return t
