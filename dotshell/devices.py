"""Device roles as small protocols (structural typing: a backend needs no base class).

Contract v2 (documented for driver authors in ``docs/devices.md``):

* Every device has ``connect()``, ``close()`` and ``status()``. Optional abilities are separate
  protocols a backend may also satisfy (:class:`Stoppable`, :class:`Homing`,
  :class:`ExposureControl`, :class:`FrameInfoSource`, :class:`AngleReadback`,
  :class:`Identified`, :class:`SequencedProjector`, :class:`TriggeredCamera`, ...).
* Roles and capabilities are checked **from the class**, never by calling a property:
  :func:`implements` / :func:`missing_members`. (``isinstance`` with a runtime-checkable
  protocol calls every property on Python 3.11, which would touch hardware before ``connect()``.)
* Properties (``resolution``, ``bit_depth``, ``position``) are **cheap and hardware-free**: they
  return what the driver knows (settings, the last reply). Anything that talks to the device is
  a method.
* Failures: raise :class:`dotshell.errors.DeviceError` for a recoverable per-step failure (it
  is retried), :class:`dotshell.errors.DeviceLostError` when the device is gone (the rig
  reconnects it once before the scan fails), :class:`dotshell.errors.DeviceTimeout` when it did
  not answer in time. Any other exception from a driver is wrapped by the rig as a plugin fault
  naming the plugin, role and backend.
* Drivers need not lock: the :class:`~dotshell.rig.assembly.Rig` serialises calls per device, so a
  front end may poll ``status()`` while a scan runs.

Units: angles in degrees, times in milliseconds (``*_ms``) or seconds (``*_s``), images as numpy
arrays (rows, columns).
"""

from __future__ import annotations

import inspect
from dataclasses import dataclass, field
from typing import Any, Protocol, Sequence, runtime_checkable

import numpy as np


@runtime_checkable
class Device(Protocol):
    def connect(self) -> None:
        """Open the device. Raise :class:`dotshell.errors.DeviceError` with a fix on failure.
        May be called again after :meth:`close` or after a lost device (reconnect)."""
        ...

    def close(self) -> None:
        """Release the device; must be safe to call twice and after a failed connect."""
        ...

    def status(self) -> dict[str, Any]:
        """Live state for front ends, e.g. ``{"connected": True, "angle_deg": 30.0}``. Cheap:
        front ends poll it about once a second."""
        ...


@runtime_checkable
class Camera(Device, Protocol):
    @property
    def resolution(self) -> tuple[int, int]:
        """(width, height) in pixels. Hardware-free (from settings or the last connect)."""
        ...

    @property
    def bit_depth(self) -> int:
        """Bits per pixel of captured frames (8 → uint8, 9..16 → uint16, values below
        ``2**bit_depth``). Hardware-free."""
        ...

    def capture(self) -> np.ndarray:
        """Expose and read one frame: 2-D, shape (height, width), uint8 or uint16."""
        ...


@runtime_checkable
class Projector(Device, Protocol):
    @property
    def resolution(self) -> tuple[int, int]:
        """(width, height) in pixels. Hardware-free."""
        ...

    def show(self, pattern: np.ndarray, name: str = "", index: int = -1) -> None:
        """Display a uint8 (height, width) image until the next call. ``name`` and ``index``
        identify the pattern in the coding's sequence (``""``/``-1`` for ad-hoc images); a
        driver with the patterns stored on the device may show the stored one. Drivers written
        for contract v1 (``show(self, pattern)``) still work: the rig passes only what the
        method accepts."""
        ...


@runtime_checkable
class Stage(Device, Protocol):
    def move_to(self, degrees: float) -> None:
        """Rotate to an absolute angle (degrees) and return when settled."""
        ...

    @property
    def position(self) -> float:
        """Last known angle in degrees (commanded or last read back). Hardware-free."""
        ...


@runtime_checkable
class Analyzer(Device, Protocol):
    def set_angle(self, degrees: float) -> None:
        """Set the analyzer's transmission axis relative to the polarizer (degrees); return
        when settled."""
        ...


@runtime_checkable
class LightSource(Device, Protocol):
    def set(self, on: bool) -> None:
        """Switch the source (e.g. trans-illumination laser) on or off."""
        ...


#: The protocol of each device role.
ROLE_PROTOCOLS: dict[str, type] = {
    "camera": Camera,
    "projector": Projector,
    "stage": Stage,
    "analyzer": Analyzer,
    "light_source": LightSource,
}


# ---- optional capabilities -------------------------------------------------------------------

@runtime_checkable
class Stoppable(Protocol):
    def stop(self) -> None:
        """Stop any motion now (feed hold, halt, stop command) and return within ~0.1 s. Called
        from another thread than the one waiting in ``move_to``/``set_angle``, which should
        then raise :class:`dotshell.errors.DeviceError` ("stopped"). Idempotent; must not raise
        when nothing moves or the device is closed."""
        ...


@runtime_checkable
class Homing(Protocol):
    def home(self) -> None:
        """Find the stage's reference position (0°); return when done."""
        ...


@runtime_checkable
class ExposureControl(Protocol):
    def set_exposure(self, ms: float) -> None:
        """Set the exposure time in milliseconds."""
        ...


@dataclass(frozen=True)
class FrameInfo:
    """What a camera knows about the frame it returned last.

    Attributes:
        timestamp_s: when the exposure started (camera clock or host ``time.time()``), seconds.
        frame_id: the camera's frame counter (-1 if unknown).
        exposure_ms: the exposure actually used (NaN if unknown).
        extra: any other driver-specific values (gain, temperature, trigger source, ...);
            JSON-serialisable.
    """

    timestamp_s: float
    frame_id: int = -1
    exposure_ms: float = float("nan")
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {"timestamp_s": self.timestamp_s, "frame_id": self.frame_id,
                "exposure_ms": self.exposure_ms, **self.extra}


@runtime_checkable
class FrameInfoSource(Protocol):
    def last_frame_info(self) -> FrameInfo:
        """Metadata of the frame the last ``capture()`` returned (hardware-free)."""
        ...


@runtime_checkable
class AngleReadback(Protocol):
    def read_angle(self) -> float:
        """Ask the device where it is now (degrees). The runner records it per view as the
        angle actually reached."""
        ...


@dataclass(frozen=True)
class DeviceIdentity:
    """Who a device is, recorded in the run's manifest at connect."""

    model: str = ""
    serial_number: str = ""
    firmware: str = ""
    vendor: str = ""

    def to_dict(self) -> dict[str, str]:
        return {k: v for k, v in vars(self).items() if v}


@runtime_checkable
class Identified(Protocol):
    def identity(self) -> DeviceIdentity:
        """Model, serial number, firmware as read from the device at connect."""
        ...


@dataclass(frozen=True)
class SequencePattern:
    """One pattern of a hardware sequence: its image, name and index in the coding."""

    image: np.ndarray
    name: str
    index: int


@runtime_checkable
class SequencedProjector(Protocol):
    """A projector that stores a pattern sequence and steps through it on its own, with a
    trigger output per pattern (DLP LightCrafter pattern mode)."""

    def shortest_period_ms(self, exposure_ms: float, at_least_ms: float) -> float:
        """The shortest pattern period (ms) the projector can run with this pattern exposure
        that is at least ``at_least_ms`` (e.g. a LightCrafter takes a period equal to the
        exposure or at least 0.23 ms longer). Hardware-free."""
        ...

    def load_sequence(self, patterns: Sequence[SequencePattern], exposure_ms: float,
                      period_ms: float) -> None:
        """Store ``patterns`` on the device, each shown for ``period_ms`` with the trigger out
        asserted for ``exposure_ms``."""
        ...

    def start_sequence(self) -> None:
        """Run the loaded sequence once from its first pattern."""
        ...

    def stop_sequence(self) -> None:
        """Stop a running sequence (idempotent)."""
        ...


@runtime_checkable
class TriggeredCamera(Protocol):
    """A camera that can be armed for N externally triggered frames."""

    def min_trigger_period_ms(self, exposure_ms: float) -> float:
        """Shortest time between trigger edges (ms) the camera keeps up with at this exposure
        (exposure plus readout, or the longer of the two for sensors that read out while the
        next frame exposes). The runner chooses the pattern period from it: faster edges are
        missed and the view times out. Hardware-free."""
        ...

    def arm(self, n_frames: int, exposure_ms: float) -> None:
        """Prepare to take ``n_frames`` frames, one per trigger edge."""
        ...

    def read_armed(self, timeout_s: float) -> list[tuple[np.ndarray, FrameInfo]]:
        """Wait for the armed frames; :class:`dotshell.errors.DeviceTimeout` after
        ``timeout_s`` seconds naming how many arrived."""
        ...

    def disarm(self) -> None:
        """Leave triggered mode (idempotent)."""
        ...


@runtime_checkable
class GroundTruth(Protocol):
    """A simulated device that knows the true rig geometry (the simulator's camera)."""

    def ground_truth_calibration(self):  # -> dotshell.geometry.calibration.RigCalibration
        ...


@runtime_checkable
class Targetable(Protocol):
    """A light source whose beam can be pointed (galvo mirrors, a translation stage)."""

    def aim(self, target_mm: tuple[float, float]) -> None:
        """Point the beam at ``target_mm`` = (lateral, height) in mm in the source's own target
        plane (for the simulator: the stage frame's y and z, the beam entering the far side and
        running along +x, towards the camera). Return when the beam has settled."""
        ...


@runtime_checkable
class FlatFieldReference(Protocol):
    """A rig that can show the camera a uniform radiance field (a diffuser or integrating
    sphere port in front of the lens) for flat-field / vignetting correction."""

    def flat_field(self, on: bool) -> None:
        """Put the uniform reference in front of the camera (True) or take it away (False)."""
        ...


@dataclass
class SurfaceRadiance:
    """The true radiance leaving a sample along its surface normal (the paper's I0), as a field
    on the true surface: ``radiance`` per vertex, linear on each triangle. Units: camera DN
    per ms of exposure that a dark-subtracted, flat-fielded pixel at the principal point would
    record from a surface element facing the camera squarely. At a point the field is read at
    its closest surface point; a point farther than ``max_snap_mm`` from the surface has none.
    """

    vertices_mm: np.ndarray   #: (V, 3) sample frame, mm
    triangles: np.ndarray     #: (T, 3) 0-based vertex indices
    radiance: np.ndarray      #: (V,) DN per ms
    max_snap_mm: float = 1.0


@runtime_checkable
class TransilluminationTruth(Protocol):
    """A simulated light source that knows the true light leaving the sample. A scan records
    it in the run (``truth.json``, docs/run-directory.md) for every trans-illuminated view and
    source; validation reads it from there."""

    def true_surface_radiance(self, angle_deg: float,
                              target_mm: tuple[float, float] | None) -> SurfaceRadiance:
        """The true light for the stage at ``angle_deg`` and the beam at ``target_mm`` (None =
        where it points now: an un-aimed source). Works on devices built but not connected."""
        ...


# ---- checks from the class -------------------------------------------------------------------

def _members(protocol: type) -> list[str]:
    names: set[str] = set()
    for klass in protocol.__mro__:
        if klass in (object, Protocol) or klass.__name__ in ("Protocol", "Generic"):
            continue
        names.update(n for n in vars(klass) if not n.startswith("_"))
    return sorted(names)


def _is_property(protocol: type, name: str) -> bool:
    return any(isinstance(vars(k).get(name), property) for k in protocol.__mro__)


def missing_members(obj: Any, protocol: type) -> list[str]:
    """The members of ``protocol`` that ``obj`` lacks, found on its class (or set on the
    instance), without calling any property. A rig's device handle is looked through to the
    driver behind it; another proxy class with ``__getattr__`` is asked for the protocol's
    methods (never its properties) by name."""
    if getattr(type(obj), "_wraps_device", False):
        obj = vars(obj)["_device"]
    cls = type(obj)
    inst = getattr(obj, "__dict__", {})
    proxy = any("__getattr__" in vars(k) for k in cls.__mro__ if k is not object)

    def has(n: str) -> bool:
        if any(n in vars(k) for k in cls.__mro__) or n in inst:
            return True
        return proxy and not _is_property(protocol, n) and hasattr(obj, n)

    return [n for n in _members(protocol) if not has(n)]


def implements(obj: Any, protocol: type) -> bool:
    """True if ``obj`` has every member of ``protocol`` (checked on the class, hardware-free)."""
    return not missing_members(obj, protocol)


def accepted_kwargs(method: Any, names: Sequence[str]) -> tuple[str, ...]:
    """Which of ``names`` a bound ``method`` accepts as keywords (for contract-v1 drivers)."""
    try:
        params = inspect.signature(method).parameters
    except (TypeError, ValueError):
        return ()
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        return tuple(names)
    return tuple(n for n in names if n in params)
