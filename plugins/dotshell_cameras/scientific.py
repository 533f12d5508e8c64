"""Scientific cameras (EMCCD / sCMOS) through pylablib's camera classes. Optional extra:
``pip install 'dotshell[pylablib]'`` plus the vendor's SDK (Andor SDK2/SDK3, Hamamatsu DCAM-API,
PCO SDK, Thorlabs Scientific Camera SDK, IDS uc480 / ThorCam).

pylablib's documented camera interface (pylablib.readthedocs.io, "Cameras"): ``open()``,
``close()``, ``get_device_info()``, ``set_exposure(seconds)`` / ``get_exposure()``,
``get_detector_size()`` → (width, height), ``set_roi(hstart, hend, vstart, vend, hbin, vbin)``,
``get_data_dimensions()`` → (rows, columns), ``set_trigger_mode("int" | "ext" | ...)``,
``start_acquisition(mode="sequence", nframes=...)``, ``stop_acquisition()``,
``wait_for_frame(since="lastread", nframes, timeout)`` (raises the camera's
``TimeoutError``), ``read_multiple_images(return_info=True)`` → frames and per-frame info
(frame index, timestamps, ...), ``snap(timeout, return_info=True)``, ``get_frame_timings()`` →
(exposure, frame period) in seconds; Andor cameras add ``set_EMCCD_gain``, ``set_temperature``,
``get_temperature``, ``get_temperature_status``.

Verified here against a stand-in implementing that interface (tests/test_cameras.py) only; no
model has run this code on hardware yet (docs/hardware.md).
"""

from __future__ import annotations

import importlib
import math
from typing import Any, Callable

import numpy as np

from dotshell.devices import DeviceIdentity, FrameInfo
from dotshell.errors import DeviceError, DeviceTimeout
from dotshell.settings import Setting
from dotshell_cameras.base import CameraBase

#: model → (pylablib module, class)
MODELS = {
    "andor-sdk2": ("pylablib.devices.Andor", "AndorSDK2Camera"),
    "andor-sdk3": ("pylablib.devices.Andor", "AndorSDK3Camera"),
    "dcam": ("pylablib.devices.DCAM", "DCAMCamera"),
    "pco": ("pylablib.devices.PCO", "PCOSC2Camera"),
    "thorlabs-tlcam": ("pylablib.devices.Thorlabs", "ThorlabsTLCamera"),
    "uc480": ("pylablib.devices.uc480", "UC480Camera"),
}

SETTINGS_SCHEMA: dict[str, Setting] = {
    "model": Setting("str", "andor-sdk2", "camera family (pylablib class)",
                     choices=tuple(MODELS)),
    "index": Setting("int", 0, "camera index among the SDK's cameras", min=0),
    "em_gain": Setting("int", -1, "EMCCD gain (Andor SDK2); -1 = leave it", min=-1),
    "temperature_c": Setting("float", None, "sensor set-point; cooling on when given", "°C"),
    "roi": Setting("list[int]", [], "region of interest [hstart, hend, vstart, vend] in "
                   "sensor pixels; empty = full sensor"),
    "binning": Setting("list[int]", [1, 1], "[horizontal, vertical] binning", length=2, min=1),
    "external_trigger": Setting("str", "ext", "pylablib trigger mode for frames started by the "
                                "projector's trigger output"),
    "timeout_ms": Setting("int", 5000, "a frame that takes longer fails", "ms", min=1),
    "bit_depth": Setting("int", 16, "bits of the frames (uint16)", "bit", min=9, max=16),
}


def _pylablib_class(model: str) -> Callable[..., Any]:
    module, name = MODELS[model]
    try:
        return getattr(importlib.import_module(module), name)
    except ImportError as exc:
        raise DeviceError(f"scientific camera: cannot import {module}.{name} ({exc}); pip "
                          "install 'dotshell[pylablib]' and the vendor SDK.") from None


class ScientificCamera(CameraBase):
    """Camera, ExposureControl, TriggeredCamera, FrameInfoSource and Identified over pylablib."""

    def __init__(self, settings: dict[str, Any],
                 camera_factory: Callable[[int], Any] | None = None) -> None:
        super().__init__(settings)
        self.factory = camera_factory
        self.cam: Any = None
        self.frame_period_ms = 0.0
        self.ident = DeviceIdentity()
        self._armed: int | None = None

    def _try(self, name: str, action: Callable[[], Any]) -> bool:
        try:
            action()
        except Exception as exc:  # pylablib DeviceError subclasses, AttributeError (no such call)
            self.refused[name] = f"{type(exc).__name__}: {exc}"
            return False
        self.refused.pop(name, None)
        return True

    def connect(self) -> None:
        s = self.settings
        make = self.factory or _pylablib_class(s["model"])
        try:
            self.cam = make(s["index"])
            if not self.cam.is_opened():
                self.cam.open()
        except DeviceError:
            raise
        except Exception as exc:
            raise DeviceError(f"scientific camera: cannot open {s['model']} camera "
                              f"{s['index']} ({type(exc).__name__}: {exc}); is the vendor SDK "
                              "installed and the camera powered?") from None
        self.refused = {}
        info = self.cam.get_device_info()
        fields = info._asdict() if hasattr(info, "_asdict") else {}
        self.ident = DeviceIdentity(model=str(fields.get("model", fields.get("name", s["model"]))),
                                    serial_number=str(fields.get("serial_number", "")),
                                    vendor=s["model"].split("-")[0])
        width, height = self.cam.get_detector_size()
        roi = s["roi"] or [0, width, 0, height]
        if len(roi) != 4:
            raise DeviceError("scientific camera: roi must be [hstart, hend, vstart, vend].")
        self._try("roi", lambda: self.cam.set_roi(*roi, *s["binning"]))
        if s["em_gain"] >= 0:
            self._try("em_gain", lambda: self.cam.set_EMCCD_gain(s["em_gain"]))
        if s["temperature_c"] is not None:
            self._try("temperature_c", lambda: self.cam.set_temperature(s["temperature_c"]))
        self._try("trigger_mode", lambda: self.cam.set_trigger_mode("int"))
        rows, cols = self.cam.get_data_dimensions()
        self.size = (int(cols), int(rows))
        self._timings()

    def close(self) -> None:
        if self.cam is not None:
            try:
                self.cam.stop_acquisition()
                self.cam.close()
            except Exception:  # closing must not raise
                pass
            self.cam = None

    def identity(self) -> DeviceIdentity:
        return self.ident

    def status(self) -> dict[str, Any]:
        out: dict[str, Any] = {"connected": self.cam is not None, "resolution": list(self.size),
                               "exposure_ms": self.exposure_ms,
                               "armed": self._armed is not None,
                               "refused_controls": dict(self.refused)}
        if self.cam is not None and self.settings["temperature_c"] is not None:
            for key, call in (("temperature_c", "get_temperature"),
                              ("cooling", "get_temperature_status")):
                try:
                    out[key] = getattr(self.cam, call)()
                except Exception:  # not every model reports it
                    pass
        return out

    def _timings(self) -> None:
        try:
            exposure_s, period_s = self.cam.get_frame_timings()
        except Exception:
            return
        self.exposure_ms = float(exposure_s) * 1000.0
        self.frame_period_ms = float(period_s) * 1000.0

    def set_exposure(self, ms: float) -> None:
        if self.cam is None:
            raise DeviceError("scientific camera: not connected; connect the rig first.")
        if self._try("exposure_ms", lambda: self.cam.set_exposure(float(ms) / 1000.0)):
            self._timings()
            if math.isfinite(self.exposure_ms) and abs(self.exposure_ms - ms) > 0.01 * ms:
                self.refused["exposure_ms"] = (f"asked {ms} ms, the camera set "
                                               f"{self.exposure_ms:.4g} ms")

    # ---- frames ------------------------------------------------------------------------------

    def _frame_info(self, info: Any) -> FrameInfo:
        fields = info._asdict() if hasattr(info, "_asdict") else {}
        stamp = fields.get("timestamp_dev", fields.get("timestamp_system", float("nan")))
        extra = {k: v for k, v in fields.items() if isinstance(v, (int, float, str))}
        return FrameInfo(timestamp_s=float(stamp) if stamp is not None else float("nan"),
                         frame_id=int(fields.get("frame_index", -1)),
                         exposure_ms=self.exposure_ms, extra=extra)

    def capture(self) -> np.ndarray:
        if self.cam is None:
            raise DeviceError("scientific camera: not connected; connect the rig first.")
        try:
            frame, info = self.cam.snap(timeout=self.settings["timeout_ms"] / 1000.0,
                                        return_info=True)
        except self.cam.TimeoutError:
            raise DeviceTimeout(f"scientific camera: no frame within "
                                f"{self.settings['timeout_ms']} ms.") from None
        self._info = self._frame_info(info)
        return np.asarray(frame, np.uint16)

    def min_trigger_period_ms(self, exposure_ms: float) -> float:
        """The camera's frame period at the current exposure (from get_frame_timings), at
        least the exposure."""
        return max(float(exposure_ms), self.frame_period_ms)

    def arm(self, n_frames: int, exposure_ms: float) -> None:
        self.set_exposure(exposure_ms)
        mode = self.settings["external_trigger"]
        if not self._try("trigger_mode", lambda: self.cam.set_trigger_mode(mode)):
            raise DeviceError(f"scientific camera: trigger mode {mode!r} refused: "
                              f"{self.refused['trigger_mode']}.")
        self.cam.start_acquisition(mode="sequence", nframes=n_frames)
        self._armed = n_frames

    def read_armed(self, timeout_s: float) -> list[tuple[np.ndarray, FrameInfo]]:
        if self._armed is None:
            raise DeviceError("scientific camera: read_armed() before arm().")
        wanted = self._armed
        try:
            self.cam.wait_for_frame(since="lastread", nframes=wanted, timeout=timeout_s)
        except self.cam.TimeoutError:
            got = self.cam.read_multiple_images(return_info=True)[0]
            raise DeviceTimeout(f"scientific camera: {len(got)} of {wanted} triggered frames "
                                f"arrived within {timeout_s:.3f} s; check the trigger wiring "
                                "and trigger mode.") from None
        frames, infos = self.cam.read_multiple_images(return_info=True)
        return [(np.asarray(f, np.uint16), self._frame_info(i))
                for f, i in zip(frames[:wanted], infos[:wanted])]

    def disarm(self) -> None:
        if self.cam is None or self._armed is None:
            return
        self._armed = None
        self.cam.stop_acquisition()
        self._try("trigger_mode", lambda: self.cam.set_trigger_mode("int"))
