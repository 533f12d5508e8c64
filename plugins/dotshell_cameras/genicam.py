"""GenICam cameras (Basler, FLIR, Allied Vision, IDS, Baumer, ...) through ``harvesters`` and a
GenTL producer (the vendor's ``.cti`` file). Optional extra: ``pip install 'dotshell[genicam]'``.

harvesters (documentation: harvesters.readthedocs.io): ``Harvester().add_file(cti)``,
``update()``, ``device_info_list``, ``create(search_key)`` → ``ImageAcquirer`` with
``remote_device.node_map`` (the camera's GenICam features), ``start()``, ``stop()``,
``fetch(timeout=s)`` (raises ``genicam.gentl.TimeoutException``) returning a buffer whose
``payload.components[0]`` holds ``data``, ``width``, ``height``; ``buffer.queue()`` hands it
back. Feature names follow the GenICam SFNC: ``ExposureAuto``, ``ExposureTime`` (µs),
``GainAuto``, ``Gain`` (dB), ``PixelFormat`` (Mono8, Mono12, ...), ``TriggerSelector`` =
FrameStart, ``TriggerMode``, ``TriggerSource`` (Software, Line1, ...), ``TriggerActivation``,
``TriggerSoftware``, ``SensorReadoutTime`` (µs, where the camera has it).

Frames: ``capture()`` fires a software trigger (TriggerSource = Software) after dropping any
frame already delivered, so every frame starts after the call. ``arm(n)`` switches the trigger
source to ``trigger_source`` (the line wired to the projector's trigger output) and
``read_armed`` fetches the n frames. Every feature the camera refuses (missing, read-only,
out of range) is recorded in ``status()["refused_controls"]``.

What was verified here: the lazy import, the messages for a missing extra, a missing ``.cti``
and no producer/device, against the real harvesters 1.4 and genicam packages; the control,
trigger and fetch logic against a stand-in acquirer (tests/test_cameras.py). No GenTL producer
could be installed on the development machine (none is published on PyPI or Debian), so no
real camera or producer has run this code yet.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from dotshell.devices import DeviceIdentity, FrameInfo
from dotshell.errors import DeviceError, DeviceTimeout
from dotshell.settings import Setting
from dotshell_cameras.base import CameraBase

SETTINGS_SCHEMA: dict[str, Setting] = {
    "cti": Setting("list[str]", [], "GenTL producer files (.cti); empty = every .cti in the "
                   "directories of GENICAM_GENTL64_PATH"),
    "serial_number": Setting("str", "", "camera to open; empty = the first found"),
    "pixel_format": Setting("str", "Mono12", "GenICam PixelFormat",
                            choices=("Mono8", "Mono10", "Mono12", "Mono16")),
    "gain_db": Setting("float", -1.0, "Gain in dB (GainAuto off); -1 = leave it", "dB",
                       min=-1.0),
    "trigger_source": Setting("str", "Line1", "input line wired to the projector's trigger "
                              "output (hardware-sequenced acquisition)"),
    "trigger_activation": Setting("str", "RisingEdge", "edge that starts an exposure",
                                  choices=("RisingEdge", "FallingEdge")),
    "timeout_ms": Setting("int", 2000, "a software-triggered frame that takes longer fails",
                          "ms", min=1),
}

_BITS = {"Mono8": 8, "Mono10": 10, "Mono12": 12, "Mono16": 16}


def _harvesters() -> Any:
    try:
        from harvesters.core import Harvester
    except ImportError:
        raise DeviceError("genicam camera: harvesters is not installed; pip install "
                          "'dotshell[genicam]' and install your camera vendor's GenTL producer "
                          "(.cti).") from None
    return Harvester


def producer_files(cti: list[str], base_dir: str) -> list[str]:
    """The .cti files to load: the settings', else those on GENICAM_GENTL64_PATH."""
    if cti:
        return [p if Path(p).is_absolute() else str(Path(base_dir) / p) for p in cti]
    found = []
    for d in os.environ.get("GENICAM_GENTL64_PATH", "").split(os.pathsep):
        if d and Path(d).is_dir():
            found += sorted(str(p) for p in Path(d).glob("*.cti"))
    return found


class GenICamCamera(CameraBase):
    """Camera, ExposureControl, TriggeredCamera, FrameInfoSource and Identified."""

    def __init__(self, settings: dict[str, Any], base_dir: str = ".",
                 harvester_factory: Callable[[], Any] | None = None) -> None:
        super().__init__(settings)
        self.base_dir = base_dir
        self.harvester_factory = harvester_factory
        self.harvester: Any = None
        self.ia: Any = None
        self.readout_ms = 0.0
        self.ident = DeviceIdentity()
        self._armed: int | None = None

    @property
    def bit_depth(self) -> int:
        return _BITS[self.settings["pixel_format"]]

    @property
    def nodes(self) -> Any:
        if self.ia is None:
            raise DeviceError("genicam camera: not connected; connect the rig first.")
        return self.ia.remote_device.node_map

    # ---- Device ------------------------------------------------------------------------------

    def connect(self) -> None:
        h = (self.harvester_factory or _harvesters())()
        files = producer_files(self.settings["cti"], self.base_dir)
        if not files:
            raise DeviceError("genicam camera: no GenTL producer configured; install your "
                              "camera vendor's SDK and list its .cti in [camera.settings] cti "
                              "(or set GENICAM_GENTL64_PATH).")
        for f in files:
            if not Path(f).is_file():
                raise DeviceError(f"genicam camera: GenTL producer {f} does not exist; fix "
                                  "[camera.settings] cti.")
            h.add_file(f)
        h.update()
        serial = self.settings["serial_number"]
        infos = list(h.device_info_list)
        if not infos:
            h.reset()
            raise DeviceError(f"genicam camera: the producers ({', '.join(files)}) found no "
                              "camera; check the cable, power and (GigE) the network "
                              "settings.")
        key = {"serial_number": serial} if serial else 0
        try:
            self.ia = h.create(key)
        except Exception as exc:  # harvesters raises ValueError / GenTL exceptions
            h.reset()
            raise DeviceError(f"genicam camera: cannot open camera "
                              f"{serial or 'number 0'} ({exc}).") from None
        self.harvester = h
        self.refused = {}
        n = self.nodes
        self.ident = DeviceIdentity(model=_get(n, "DeviceModelName"),
                                    serial_number=_get(n, "DeviceSerialNumber"),
                                    firmware=_get(n, "DeviceFirmwareVersion"),
                                    vendor=_get(n, "DeviceVendorName"))
        self._set("pixel_format", "PixelFormat", self.settings["pixel_format"])
        self._set("exposure_auto", "ExposureAuto", "Off")
        if self.settings["gain_db"] >= 0:
            self._set("gain_auto", "GainAuto", "Off")
            self._set("gain_db", "Gain", float(self.settings["gain_db"]))
        self._set("trigger_selector", "TriggerSelector", "FrameStart")
        self._set("trigger_mode", "TriggerMode", "On")
        self._set("trigger_source", "TriggerSource", "Software")
        readout_us = _get(n, "SensorReadoutTime", 0.0)
        self.readout_ms = float(readout_us) / 1000.0 if readout_us else 0.0
        self.size = (int(_get(n, "Width", 0)), int(_get(n, "Height", 0)))
        self.ia.start()

    def close(self) -> None:
        if self.ia is not None:
            for step in (self.ia.stop, self.ia.destroy):
                try:
                    step()
                except Exception:  # closing must not raise
                    pass
            self.ia = None
        if self.harvester is not None:
            try:
                self.harvester.reset()
            except Exception:
                pass
            self.harvester = None

    def identity(self) -> DeviceIdentity:
        return self.ident

    def status(self) -> dict[str, Any]:
        return {"connected": self.ia is not None, "resolution": list(self.size),
                "pixel_format": self.settings["pixel_format"], "exposure_ms": self.exposure_ms,
                "armed": self._armed is not None, "refused_controls": dict(self.refused)}

    # ---- controls ----------------------------------------------------------------------------

    def _set(self, name: str, feature: str, value: Any) -> bool:
        node = getattr(self.nodes, feature, None)
        if node is None:
            self.refused[name] = f"the camera has no {feature} feature"
            return False
        try:
            node.value = value
        except Exception as exc:  # GenICam AccessException, OutOfRangeException, ...
            self.refused[name] = f"{feature} = {value!r} refused: {exc}"
            return False
        self.refused.pop(name, None)
        return True

    def set_exposure(self, ms: float) -> None:
        if self._set("exposure_ms", "ExposureTime", float(ms) * 1000.0):
            self.exposure_ms = float(self.nodes.ExposureTime.value) / 1000.0

    # ---- frames ------------------------------------------------------------------------------

    def _fetch(self, timeout_s: float) -> tuple[np.ndarray, FrameInfo]:
        from genicam.gentl import TimeoutException

        try:
            buffer = self.ia.fetch(timeout=timeout_s)
        except TimeoutException:
            raise DeviceTimeout(f"genicam camera {self.ident.serial_number}: no frame within "
                                f"{timeout_s:.3f} s.") from None
        try:
            c = buffer.payload.components[0]
            image = np.array(c.data, copy=True).reshape(c.height, c.width)
            info = FrameInfo(timestamp_s=float(buffer.timestamp_ns) / 1e9,
                             frame_id=int(getattr(buffer, "frame_id", -1)),
                             exposure_ms=self.exposure_ms,
                             extra={"trigger": "armed" if self._armed else "software"})
        finally:
            buffer.queue()
        dtype = np.uint8 if self.bit_depth == 8 else np.uint16
        return image.astype(dtype, copy=False), info

    def _drop_delivered(self) -> None:
        while True:
            buffer = self.ia.try_fetch(timeout=0.0)
            if buffer is None:
                return
            buffer.queue()

    def capture(self) -> np.ndarray:
        if self.ia is None:
            raise DeviceError("genicam camera: not connected; connect the rig first.")
        self._drop_delivered()
        self.nodes.TriggerSoftware.execute()
        image, self._info = self._fetch(self.settings["timeout_ms"] / 1000.0)
        return image

    def min_trigger_period_ms(self, exposure_ms: float) -> float:
        """Exposure plus the sensor readout (no overlap assumed: safe for every camera)."""
        return float(exposure_ms) + self.readout_ms

    def arm(self, n_frames: int, exposure_ms: float) -> None:
        self.ia.stop()
        self.set_exposure(exposure_ms)
        ok = self._set("trigger_source", "TriggerSource", self.settings["trigger_source"])
        self._set("trigger_activation", "TriggerActivation",
                  self.settings["trigger_activation"])
        if not ok:
            raise DeviceError(f"genicam camera: cannot trigger from "
                              f"{self.settings['trigger_source']}: "
                              f"{self.refused['trigger_source']}.")
        self.ia.start()
        self._armed = n_frames

    def read_armed(self, timeout_s: float) -> list[tuple[np.ndarray, FrameInfo]]:
        if self._armed is None:
            raise DeviceError("genicam camera: read_armed() before arm().")
        deadline = time.monotonic() + timeout_s
        frames = []
        try:
            while len(frames) < self._armed:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise DeviceTimeout("")
                frames.append(self._fetch(left))
        except DeviceTimeout:
            raise DeviceTimeout(f"genicam camera: {len(frames)} of {self._armed} triggered "
                                f"frames arrived within {timeout_s:.3f} s; check the trigger "
                                f"wiring to {self.settings['trigger_source']}.") from None
        return frames

    def disarm(self) -> None:
        if self.ia is None or self._armed is None:
            return
        self._armed = None
        self.ia.stop()
        self._set("trigger_source", "TriggerSource", "Software")
        self.ia.start()


def _get(nodes: Any, feature: str, default: Any = "") -> Any:
    try:
        return getattr(nodes, feature).value
    except Exception:  # absent or unreadable feature
        return default
