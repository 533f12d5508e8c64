"""The Rig: builds the profile's devices through their plugins, connects and closes them."""

from __future__ import annotations

from typing import Any

from dotshell import devices
from dotshell.backends import RigContext
from dotshell.errors import CalibrationError, DeviceError, PluginError
from dotshell.geometry.calibration import RigCalibration
from dotshell.plugins import PluginManager
from dotshell.profile import DEVICE_ROLES, Profile

PROTOCOLS = devices.ROLE_PROTOCOLS


class Rig:
    """The devices of one profile. Use as a context manager to connect and always close::

        with Rig(profile, pm) as rig:
            rig.stage.move_to(30)
    """

    def __init__(self, profile: Profile, pm: PluginManager) -> None:
        self.profile = profile
        self.context = RigContext(base_dir=str(profile.base_dir))
        self.devices: dict[str, Any] = {}
        self.connected: list[str] = []
        for role in DEVICE_ROLES:
            section = profile.role(role)
            if section is None:
                continue
            dev = pm.create(role, section["backend"], section["settings"], self.context,
                            profile.source)
            missing = devices.missing_members(dev, PROTOCOLS[role])
            if missing:
                raise PluginError(f"backend {section['backend']!r} for role {role} returned a "
                                  f"{type(dev).__name__}, which lacks {', '.join(missing)} of "
                                  f"the {role} protocol (see docs/devices.md); fix the plugin.")
            self.devices[role] = dev

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

    def connect(self) -> None:
        """Connect every device in role order; on failure close the ones already open."""
        for role, dev in self.devices.items():
            if role in self.connected:
                continue
            try:
                dev.connect()
            except DeviceError as exc:
                self.close()
                backend = self.profile.role(role)["backend"]
                raise DeviceError(f"{role} ({backend}) failed to connect: {exc}") from None
            self.connected.append(role)

    def close(self) -> None:
        """Close every connected device (in reverse order); never raises for a device."""
        for role in reversed(self.connected):
            try:
                self.devices[role].close()
            except Exception:  # closing must not mask the original error
                pass
        self.connected.clear()

    def stop(self) -> None:
        """Stop every device that can move (:class:`~dotshell.devices.Stoppable`) now; called
        on abort, Ctrl-C, SIGTERM and SIGHUP, possibly from another thread. Never raises."""
        for dev in self.devices.values():
            if devices.implements(dev, devices.Stoppable):
                try:
                    dev.stop()
                except Exception:  # stopping must reach every device
                    pass

    def __enter__(self) -> "Rig":
        self.connect()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def status(self) -> dict[str, dict[str, Any]]:
        """Status of every device by role."""
        out = {}
        for role, dev in self.devices.items():
            try:
                out[role] = dev.status()
            except Exception as exc:
                out[role] = {"error": f"{type(exc).__name__}: {exc}"}
        return out

    def calibration(self, override_path: str | None = None) -> RigCalibration:
        """The calibration this rig's scans use: a file, or the simulator's ground truth."""
        if override_path:
            return RigCalibration.load(override_path)
        path = self.profile.calibration_path()
        if path is not None:
            return RigCalibration.load(path)
        for dev in self.devices.values():
            if devices.implements(dev, devices.GroundTruth):
                return dev.ground_truth_calibration()
        raise CalibrationError(
            f"{self.profile.source}: [calibration] source = \"ground-truth\" needs a simulated "
            "device that knows the true geometry; none of this profile's backends does. Use "
            "file = \"calibration.json\" with a measured calibration.")
