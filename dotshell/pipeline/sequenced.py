"""Hardware-sequenced acquisition: the projector runs a view's patterns on its own clock and its
trigger output starts each camera exposure.

The show/settle/capture path costs every frame a display latency (``settle_ms``) plus a
software-triggered exposure and readout. With a projector that stores a pattern sequence
(:class:`~dotshell.devices.SequencedProjector`, e.g. a LightCrafter 4500 in pattern mode) and a
camera armed for externally triggered frames (:class:`~dotshell.devices.TriggeredCamera`), a
view costs one pattern period per frame and no settling at all.

One *run* is one pass of the stored sequence: the shots of a view taken at one analyzer angle
(a PDI view has two runs, the analyzer turned between them). A run that fails with a
:class:`~dotshell.errors.DeviceError` (a trigger timeout, a projector error register) is
stopped, disarmed and repeated up to ``scan.retries`` times with a warning each; its frames are
kept only when the whole run arrived.

The pattern period is ``scan.pattern_period_ms`` or, when 0, the shortest both devices allow:
at least the exposure, the camera's minimum trigger period and whatever the projector needs
(:meth:`~dotshell.devices.SequencedProjector.shortest_period_ms`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from dotshell import devices
from dotshell.coding import PatternFrame
from dotshell.devices import FrameInfo, SequencePattern
from dotshell.errors import DeviceError, ProfileError
from dotshell.events import EventBus
from dotshell.pipeline.pdi import Shot

#: Extra time a run may take beyond its nominal length before it counts as timed out (s), and
#: as a share of the nominal length (USB latency, trigger delays, a slow first frame).
TIMEOUT_MARGIN_S = 1.0
TIMEOUT_MARGIN_SHARE = 0.5


def sequenced_capable(rig: Any) -> list[str]:
    """Why ``rig`` cannot acquire sequenced (empty when it can): the missing members of the
    projector's and the camera's capability."""
    why = []
    for role, dev, protocol in (("projector", rig.projector, devices.SequencedProjector),
                                ("camera", rig.camera, devices.TriggeredCamera)):
        missing = devices.missing_members(dev, protocol)
        if missing:
            backend = rig.profile.role(role)["backend"]
            why.append(f"the {role} ({backend}) lacks {', '.join(missing)}")
    return why


def uses_sequenced(rig: Any, scan: Mapping[str, Any]) -> bool:
    """Whether a scan with ``scan`` settings acquires sequenced on ``rig``; a ProfileError when
    ``acquisition = "sequenced"`` is asked of devices that cannot."""
    mode = scan.get("acquisition", "auto")
    if mode == "show-capture":
        return False
    why = sequenced_capable(rig)
    if why and mode == "sequenced":
        raise ProfileError(f"{rig.profile.source}: [scan] acquisition = \"sequenced\" needs a "
                           "projector with hardware sequences and a camera with a trigger "
                           f"input, but {' and '.join(why)}. Use acquisition = \"auto\" or "
                           "\"show-capture\" (docs/hardware.md).")
    return not why


@dataclass(frozen=True)
class Run:
    """One pass of the stored sequence: shot indices of the view, at one analyzer angle."""

    analyzer_deg: float | None
    shots: tuple[int, ...]


def plan_runs(shots: Sequence[Shot]) -> list[Run]:
    """Consecutive shots at the same analyzer angle form one run."""
    runs: list[Run] = []
    for i, shot in enumerate(shots):
        if runs and runs[-1].analyzer_deg == shot.analyzer_deg:
            runs[-1] = Run(shot.analyzer_deg, runs[-1].shots + (i,))
        else:
            runs.append(Run(shot.analyzer_deg, (i,)))
    return runs


def pattern_period_ms(projector: Any, camera: Any, exposure_ms: float,
                      asked_ms: float = 0.0) -> float:
    """The pattern period (ms) for a sequence at ``exposure_ms``: ``asked_ms`` when given (a
    ProfileError if the camera cannot keep up), else the shortest both devices allow."""
    camera_min = float(camera.min_trigger_period_ms(exposure_ms))
    if asked_ms > 0:
        if asked_ms < max(exposure_ms, camera_min) - 1e-9:
            raise ProfileError(
                f"[scan] pattern_period_ms = {asked_ms} is shorter than the exposure "
                f"({exposure_ms} ms) or the camera's minimum trigger period ({camera_min:.3f} "
                "ms at this exposure); the camera would miss triggers. Raise it or set 0 (the "
                "shortest the devices allow).")
        return float(projector.shortest_period_ms(exposure_ms, asked_ms))
    return float(projector.shortest_period_ms(exposure_ms, max(exposure_ms, camera_min)))


class SequencedCapture:
    """The hardware-sequenced acquisition engine
    (:class:`~dotshell.pipeline.engines.AcquisitionEngine`): takes the frames of a view's shots
    as hardware-sequenced runs, a run at a time.

    :meth:`frame` hands the runner one shot's frame; the first request of a run captures the
    whole run. :meth:`holds_frames` tells the runner that frames of a captured run are still to
    be written (a stop must not drop them). ``retry(action, what)`` is the runner's retry
    policy; ``set_analyzer(degrees)`` turns the analyzer before a run."""

    name = "sequenced"

    def __init__(self, rig: Any, patterns: Sequence[PatternFrame], shots: Sequence[Shot],
                 scan: Mapping[str, Any], bus: EventBus,
                 retry: Callable[[Callable[[], Any], str], Any],
                 set_analyzer: Callable[[float], None]) -> None:
        self.rig = rig
        self.patterns = patterns
        self.shots = list(shots)
        self.runs = plan_runs(self.shots)
        self.exposure_ms = float(scan["exposure_ms"])
        self.bus = bus
        self.retry = retry
        self.set_analyzer = set_analyzer
        self.period_ms = pattern_period_ms(rig.projector, rig.camera, self.exposure_ms,
                                           float(scan.get("pattern_period_ms", 0.0)))
        self.loaded: tuple[int, ...] | None = None  # pattern indices stored on the projector
        self.buffer: dict[int, tuple[np.ndarray, FrameInfo]] = {}

    def holds_frames(self) -> bool:
        return bool(self.buffer)

    def frame(self, view: int, index: int) -> tuple[np.ndarray, FrameInfo]:
        """The frame of shot ``index`` of ``view`` and its metadata; runs its sequence if not
        yet captured."""
        if index not in self.buffer:
            run = next(r for r in self.runs if index in r.shots)
            if run.analyzer_deg is not None:
                self.set_analyzer(run.analyzer_deg)
            what = (f"view {view}, sequence of {len(run.shots)} patterns"
                    + ("" if run.analyzer_deg is None else f" at analyzer {run.analyzer_deg}°"))
            got = self.retry(lambda: self._run(run), what)
            self.buffer.update(zip(run.shots, got))
        return self.buffer.pop(index)

    def _load(self, run: Run) -> None:
        wanted = tuple(self.shots[i].pattern for i in run.shots)
        if self.loaded == wanted:
            return
        self.loaded = None
        seq = [SequencePattern(self.patterns[p].image, self.patterns[p].name, p) for p in wanted]
        self.rig.projector.load_sequence(seq, self.exposure_ms, self.period_ms)
        self.loaded = wanted

    def _run(self, run: Run) -> list[tuple[np.ndarray, FrameInfo]]:
        projector, camera = self.rig.projector, self.rig.camera
        n = len(run.shots)
        nominal_s = n * self.period_ms / 1000.0
        timeout_s = nominal_s * (1 + TIMEOUT_MARGIN_SHARE) + TIMEOUT_MARGIN_S
        try:
            self._load(run)
            camera.arm(n, self.exposure_ms)
            projector.start_sequence()
            got = camera.read_armed(timeout_s)
        finally:
            for stop in (projector.stop_sequence, camera.disarm):
                try:
                    stop()
                except DeviceError as exc:  # the run's own error (if any) is the one to report
                    self.bus.warn(f"{type(stop.__self__).__name__}.{stop.__name__}: {exc}")
        if len(got) != n:
            raise DeviceError(f"the camera returned {len(got)} frames for a sequence of {n} "
                              "patterns.")
        return list(got)
