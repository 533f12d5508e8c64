"""The Rig: builds the profile's devices through their plugins, connects, homes, stops and closes
them, and hands each out behind a :class:`~dotshell.rig.handles.DeviceHandle` (calls serialised per
device, time-limited, plugin faults named, a lost device reconnected once)."""

from __future__ import annotations

import time
from typing import Any, Callable

from dotshell import devices
from dotshell.backends import RigContext
from dotshell.errors import (CalibrationError, DeviceError, DotshellError, PluginError,
                             PluginFault, ProfileError)
from dotshell.geometry.calibration import RigCalibration
from dotshell.geometry.opencv_io import load_any_calibration
from dotshell.rig.handles import DeviceHandle, DevicePolicy, unwrap
from dotshell.rig.owners import DeviceInUse, DeviceOwnership
from dotshell.plugins import PluginManager
from dotshell.profile.loader import DEVICE_ROLES, Profile

PROTOCOLS = devices.ROLE_PROTOCOLS

#: Optional capabilities recorded per device in the manifest.
CAPABILITIES: dict[str, type] = {
    "stop": devices.Stoppable, "home": devices.Homing, "exposure": devices.ExposureControl,
    "frame_info": devices.FrameInfoSource, "angle_readback": devices.AngleReadback,
    "identity": devices.Identified, "sequenced_projector": devices.SequencedProjector,
    "triggered_camera": devices.TriggeredCamera,
}


def _policy(section: dict[str, Any]) -> DevicePolicy:
    timeouts = {k: float(v) for k, v in (section.get("timeouts") or {}).items() if v is not None}
    return DevicePolicy(timeouts_s=timeouts, reconnect=section.get("reconnect", True),
                        reconnect_wait_s=section.get("reconnect_wait_s", 10.0),
                        home=section.get("home") or "never")


class Rig:
    """The devices of one profile. Use as a context manager to connect and always close::

        with Rig(profile, pm) as rig:
            rig.stage.move_to(30)

    Attributes:
        devices: the device handles by role (each forwards to the driver object).
        connected: roles connected, in order.
        where: what the rig is doing, named in plugin-fault and timeout messages (the
            acquisition sets ``{"run": ..., "view": ..., "angle_deg": ...}``).
    """

    def __init__(self, profile: Profile, pm: PluginManager) -> None:
        self.profile = profile
        self.context = RigContext(base_dir=str(profile.base_dir))
        self.devices: dict[str, DeviceHandle] = {}
        self.policies: dict[str, DevicePolicy] = {}
        self.connected: list[str] = []
        self.where: dict[str, Any] = {}
        self.records: dict[str, dict[str, Any]] = {}
        self.messages: list[tuple[str, str, float]] = []
        self._listeners: list[Callable[[str, str, float], None]] = []
        self.owners = DeviceOwnership(str(profile.source))
        for role in DEVICE_ROLES:
            section = profile.role(role)
            if section is not None:
                self.devices[role] = self._build(role, section, pm)

    def _build(self, role: str, section: dict[str, Any], pm: PluginManager) -> DeviceHandle:
        backend, profile_source = section["backend"], self.profile.source
        info = pm.backend(role, backend, profile_source)
        context = self.context.for_device(role, backend)
        context.log.listen(self._device_message)
        try:
            dev = pm.create(role, backend, section["settings"], context, profile_source)
        except (DotshellError, MemoryError):  # MemoryError: the machine's, not the plugin's
            raise
        except Exception as exc:
            raise PluginFault(f"plugin {info.plugin!r} (role {role}, backend {backend}) raised "
                              f"{type(exc).__name__}: {exc} while building the device from "
                              f"{profile_source}. This is a bug in the plugin "
                              f"({info.distribution}); report it to its authors.") from exc
        missing = devices.missing_members(dev, PROTOCOLS[role])
        if missing:
            raise PluginError(f"backend {backend!r} for role {role} returned a "
                              f"{type(dev).__name__}, which lacks {', '.join(missing)} of "
                              f"the {role} protocol (see docs/devices.md); fix the plugin.")
        policy = self.policies[role] = _policy(section)
        if policy.home != "never" and not devices.implements(dev, devices.Homing):
            raise ProfileError(f"{profile_source}: [{role}] home = {policy.home!r}, but backend "
                               f"{backend!r} cannot home (it has no home()). Set home = "
                               "\"never\" or choose a backend that homes.")
        handle = DeviceHandle(role, backend, info.plugin, info.distribution, dev, context,
                              policy, self._where_text)
        self.context.peers[role] = handle
        return handle

    # ---- roles --------------------------------------------------------------------------------

    @property
    def camera(self) -> devices.Camera:
        return self.devices["camera"]

    @property
    def projector(self) -> devices.Projector:
        return self.devices["projector"]

    @property
    def stage(self) -> devices.Stage:
        return self.devices["stage"]

    @property
    def analyzer(self) -> devices.Analyzer | None:
        return self.devices.get("analyzer")

    @property
    def light_source(self) -> devices.LightSource | None:
        return self.devices.get("light_source")

    def backend(self, role: str) -> str:
        return self.profile.required_role(role)["backend"]

    # ---- log ----------------------------------------------------------------------------------

    def _device_message(self, level: str, text: str, when: float) -> None:
        self.messages.append((level, text, when))
        del self.messages[:-200]
        for fn in list(self._listeners):
            fn(level, text, when)

    def listen(self, fn: Callable[[str, str, float], None]) -> Callable[[], None]:
        """Call ``fn(level, text, unix_time)`` for every device log line (from any thread);
        returns the unsubscribe."""
        self._listeners.append(fn)
        return lambda: self._listeners.remove(fn) if fn in self._listeners else None

    def _where_text(self) -> str:
        w = self.where
        parts = []
        if "view" in w:
            parts.append(f"view {w['view']}")
        if "angle_deg" in w:
            parts.append(f"angle {w['angle_deg']:g}°")
        if "run" in w:
            parts.append(f"run {w['run']}")
        return f"({', '.join(parts)})" if parts else ""

    # ---- lifecycle ----------------------------------------------------------------------------

    def connect(self) -> None:
        """Connect every device in role order (a lost one is reopened), each once this process
        holds the hardware it names (:mod:`dotshell.rig.owners`); on failure close the ones already
        open. Records identity and a status snapshot per device, then homes the
        devices whose ``home = "on_connect"``."""
        for role, dev in self.devices.items():
            if role in self.connected:
                if dev.lost:
                    self._guarded(role, dev.reopen)
                continue
            self._claim(role)
            self._guarded(role, dev.connect)
            self.connected.append(role)
            self._guarded(role, lambda: self._record(role))  # noqa: B023 (called at once)
        for role, policy in self.policies.items():
            if policy.home == "on_connect":
                self._guarded(role, lambda: self.home(role))  # noqa: B023 (called at once)

    def _claim(self, role: str) -> None:
        """Hold the hardware the role's settings name (one process per device,
        :mod:`dotshell.rig.owners`); refused naming the holder, every device of this rig closed."""
        try:
            self.owners.claim(role, self.backend(role), self.profile.required_role(role)["settings"])
        except DeviceInUse:
            self.close()
            raise

    def _guarded(self, role: str, action: Callable[[], Any]) -> None:
        """``action()``; on failure close every device (this one included) and re-raise."""
        try:
            action()
        except PluginFault:
            self._close_after_failure(role)
            raise
        except DeviceError as exc:
            self._close_after_failure(role)
            raise type(exc)(f"{role} ({self.backend(role)}) failed to connect: {exc}") from None

    def _close_after_failure(self, role: str) -> None:
        if role not in self.connected:
            self.devices[role].shutdown()  # close() is safe after a failed connect()
        self.close()

    def _record(self, role: str) -> None:
        dev = self.devices[role]
        caps = [name for name, proto in CAPABILITIES.items() if devices.implements(dev, proto)]
        record: dict[str, Any] = {"backend": self.backend(role), "plugin": dev._plugin,
                                  "distribution": dev._distribution, "capabilities": caps,
                                  "connected_at": time.time()}
        if "identity" in caps:
            ident = dev.identity()
            record["identity"] = ident.to_dict() if hasattr(ident, "to_dict") else dict(ident)
        record["status"] = dev.poll_status()
        policy = self.policies[role]
        record["timeouts_s"] = {m: policy.timeout(m)[0] for m in ("connect", *_main_calls(role))}
        record["reconnect"] = policy.reconnect
        if policy.home != "never":
            record["home"] = policy.home
        self.records[role] = record

    def describe(self) -> dict[str, dict[str, Any]]:
        """Per connected device: backend, plugin, capabilities, identity (model, serial number,
        firmware), the status snapshot at connect, timeouts — written to the run's manifest."""
        return {role: dict(self.records[role]) for role in self.connected if role in self.records}

    def home(self, role: str = "stage") -> float | None:
        """Home the device filling ``role``; returns its position afterwards (degrees) if it
        reports one."""
        dev = self.devices.get(role)
        if dev is None or not devices.implements(dev, devices.Homing):
            raise DeviceError(f"cannot home the {role}: the profile's {role} "
                              f"({self.backend(role) if dev is not None else 'none'}) has no "
                              "home().")
        dev.home()
        dev._context.log.info("homed")
        pos = getattr(unwrap(dev), "position", None)
        return float(pos) if isinstance(pos, (int, float)) else None

    def close(self) -> None:
        """Close every connected device (in reverse order) and end every worker thread; never
        raises for a device."""
        for role in reversed(self.connected):
            self.devices[role].shutdown()
        for role, dev in self.devices.items():
            if role not in self.connected:
                dev.release()  # e.g. polled for status, never connected
        self.connected.clear()
        self.owners.release()

    def stop(self) -> None:
        """Stop every device that can move (:class:`~dotshell.devices.Stoppable`) now; called
        on abort, Ctrl-C, SIGTERM and SIGHUP. Takes no lock and logs nothing, so it is safe from
        another thread and from a signal handler while the main thread is inside a device call.
        Never raises."""
        for dev in list(self.devices.values()):
            if devices.implements(dev, devices.Stoppable):
                dev.stop_now()

    def __enter__(self) -> Rig:
        self.connect()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def status(self) -> dict[str, dict[str, Any]]:
        """Status of every device by role; never waits for a call in progress (a busy device
        shows its last snapshot with ``busy``)."""
        return {role: dev.poll_status() for role, dev in self.devices.items()}

    def calibration(self, override_path: str | None = None) -> RigCalibration:
        """The calibration this rig's scans use: a file, or the simulator's ground truth."""
        if override_path:
            return load_any_calibration(override_path)
        path = self.profile.calibration_path()
        if path is not None:
            return load_any_calibration(path)
        for dev in self.devices.values():
            if devices.implements(dev, devices.GroundTruth):
                return dev.ground_truth_calibration()
        raise CalibrationError(
            f"{self.profile.source}: [calibration] source = \"ground-truth\" needs a simulated "
            "device that knows the true geometry; none of this profile's backends does. Use "
            "file = \"calibration.json\" with a measured calibration.")


def _main_calls(role: str) -> tuple[str, ...]:
    return {"camera": ("capture",), "projector": ("show",), "stage": ("move_to", "home"),
            "analyzer": ("set_angle",), "light_source": ("set",)}[role]
