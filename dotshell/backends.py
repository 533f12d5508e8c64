"""What a plugin hands the core for each backend it provides, and what the core hands a device."""

from __future__ import annotations

import logging
import math
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Iterator, Mapping

from dotshell.settings import Setting

#: Roles a backend can fill, and the hook that provides them.
ROLES: dict[str, str] = {
    "camera": "dotshell_cameras",
    "projector": "dotshell_projectors",
    "stage": "dotshell_stages",
    "analyzer": "dotshell_analyzers",
    "light_source": "dotshell_light_sources",
    "coding": "dotshell_codings",
    "surface_mesher": "dotshell_surface_meshers",
    "volume_mesher": "dotshell_volume_meshers",
    "normalizer": "dotshell_normalizers",
    "exporter": "dotshell_exporters",
}

logging.getLogger("dotshell.devices").addHandler(logging.NullHandler())  # front ends show them

#: ``listener(level, text, unix_time)`` receives a device's log lines.
LogListener = Callable[[str, str, float], None]


class DeviceLog:
    """A device's log: ``info`` / ``warn`` lines that reach the run's ``events.jsonl`` and the
    front ends while a scan runs (and Python's ``logging`` always). Thread-safe; never raises.

    Args:
        who: how lines are prefixed, e.g. ``"stage (grbl)"``.
    """

    def __init__(self, who: str = "device") -> None:
        self.who = who
        self._listeners: list[LogListener] = []
        self._lock = threading.Lock()
        self._logger = logging.getLogger("dotshell.devices")

    def listen(self, listener: LogListener) -> Callable[[], None]:
        """Call ``listener(level, text, time)`` for every line; returns the unsubscribe."""
        with self._lock:
            self._listeners.append(listener)

        def unsubscribe() -> None:
            with self._lock:
                if listener in self._listeners:
                    self._listeners.remove(listener)

        return unsubscribe

    def info(self, text: str) -> None:
        self._emit("info", text)

    def warn(self, text: str) -> None:
        self._emit("warning", text)

    def _emit(self, level: str, text: str) -> None:
        line = f"{self.who}: {text}"
        self._logger.log(logging.WARNING if level == "warning" else logging.INFO, line)
        with self._lock:
            listeners = list(self._listeners)
        now = time.time()
        for fn in listeners:
            try:
                fn(level, line, now)
            except Exception:  # a front end's problem must not break the device
                pass


@dataclass
class RigContext:
    """Passed to every device factory of one rig (one context per device; ``shared`` and the
    peers are common to the rig's devices).

    Attributes:
        shared: scratch space shared by the devices of this rig (e.g. one serial bus serving a
            stage and an analyzer, or the simulator's world). Key it by your plugin name.
        base_dir: directory of the profile, for resolving relative paths in settings.
        role: the role this device fills (``""`` outside a rig, e.g. in a bare test).
        backend: the backend name the profile chose.
        log: the device's log — ``context.log.warn("limit switch touched")`` reaches the run's
            ``events.jsonl`` and the front ends.
    """

    shared: dict[str, Any] = field(default_factory=dict)
    base_dir: str = "."
    role: str = ""
    backend: str = ""
    log: DeviceLog = field(default_factory=DeviceLog)
    peers: dict[str, Any] = field(default_factory=dict, repr=False)
    deadline: float = field(default=math.inf, repr=False)
    computing_since: float = field(default=math.inf, repr=False)

    def device(self, role: str) -> Any | None:
        """The rig's device for another ``role`` (as the rig hands it out: calls serialised),
        or None. E.g. a simulated camera reads the angle of whatever stage the rig has."""
        return self.peers.get(role)

    def time_left(self) -> float:
        """Seconds left before the rig's timeout for the call in progress (``inf`` outside a
        rig call). Drivers that wait for motion use it to fail with their own, more precise
        :class:`~dotshell.errors.DeviceTimeout` before the rig's backstop does."""
        return self.current_deadline() - time.monotonic()

    @contextmanager
    def computing(self) -> Iterator[None]:
        """A block of the driver's own computation that a real device does not do (a simulator
        rendering its frames): the rig's timeout for the call in progress is extended by the
        block's duration, so a slow or busy host never turns it into a device timeout. Time
        spent waiting on hardware must stay outside such blocks, or a stalled device would
        never time out."""
        if self.computing_since != math.inf:  # nested: the outer block counts
            yield
            return
        self.computing_since = time.monotonic()
        try:
            yield
        finally:  # the deadline moves first: a reader never sees the block's time missing
            self.deadline += time.monotonic() - self.computing_since  # inf stays inf
            self.computing_since = math.inf

    def current_deadline(self) -> float:
        """The call's deadline (monotonic seconds), a computing block in progress included."""
        since = self.computing_since  # read before the deadline (see computing())
        return self.deadline + (time.monotonic() - since if since != math.inf else 0.0)

    def for_device(self, role: str, backend: str) -> RigContext:
        """A context for one device of this rig: same ``shared`` and peers, its own log."""
        return replace(self, role=role, backend=backend, log=DeviceLog(f"{role} ({backend})"),
                       deadline=math.inf, computing_since=math.inf)


@dataclass(frozen=True)
class Backend:
    """One backend for one role.

    Attributes:
        name: the name profiles use (``backend = "NAME"``), unique per role; lower-case-dashes.
        factory: ``factory(settings: dict, context: RigContext) -> object`` returning an object
            satisfying the role's protocol (see :mod:`dotshell.devices`, :mod:`dotshell.coding`).
            ``settings`` has been validated against ``settings_schema`` with defaults filled in.
        settings_schema: the keys of the profile's ``[ROLE.settings]`` table.
        summary: one line for ``dotshell plugins``.
        usb_ids: ``"vid:pid"`` (lower-case hex) of the USB devices this backend drives, so
            ``dotshell ports`` can say which backend fits a plugged-in device.
        compile_kernels: for a backend whose objects call compiled kernels (numba,
            ``cache=True``) during a scan: a function of no arguments that calls them on small
            inputs of the argument types a scan passes, so that a scan compiles them in a
            process of its own before it starts (:mod:`dotshell.pipeline.kernel_warmup`);
            ``None`` for the others.
    """

    name: str
    factory: Callable[..., Any]
    settings_schema: Mapping[str, Setting] = field(default_factory=dict)
    summary: str = ""
    usb_ids: tuple[str, ...] = ()
    compile_kernels: Callable[[], None] | None = None
