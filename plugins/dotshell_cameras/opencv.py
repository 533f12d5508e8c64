"""Cameras OpenCV opens: UVC / V4L2 devices, DirectShow / Media Foundation cameras, video files
and image sequences (``cv2.VideoCapture`` by index, device path, file or URL).

Controls are set through ``VideoCapture.set`` and read back with ``get``; a control the driver
refuses (``set`` returns False) or does not keep (the read-back differs) is recorded with the
reason in ``refused`` and shown in ``status()["refused_controls"]``, which the runner turns
into a warning in the run's events. Exposure in milliseconds is mapped to each capture API's
own unit (OpenCV ``videoio`` documentation and its backends):

* V4L2: ``CAP_PROP_EXPOSURE`` is ``V4L2_CID_EXPOSURE_ABSOLUTE`` in units of 100 µs;
  ``CAP_PROP_AUTO_EXPOSURE`` is ``V4L2_CID_EXPOSURE_AUTO`` (1 = manual, 3 = aperture priority).
* DirectShow and Media Foundation: ``CAP_PROP_EXPOSURE`` is log2 of the exposure in seconds
  (−5 ≈ 31 ms); auto exposure off is 0.25, on 0.75.
* files, image sequences, network streams: no exposure (refused, with that reason).

Stale frames: a live camera keeps a queue of finished frames (``CAP_PROP_BUFFERSIZE``); a frame
grabbed right after the projector changed may have been exposed before. ``flush_frames``
frames are grabbed and dropped before each capture (0 for files). Every read runs under
``read_timeout_ms`` on one worker thread: a driver that does not return in time raises
DeviceTimeout and leaves the camera marked stuck, so the next call raises DeviceLostError and
the rig's reconnect opens a fresh VideoCapture.
"""

from __future__ import annotations

import math
import time
from concurrent.futures import ThreadPoolExecutor, TimeoutError as FutureTimeout
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from dotshell.devices import DeviceIdentity, FrameInfo
from dotshell.errors import DeviceError, DeviceLostError, DeviceTimeout
from dotshell.settings import Setting
from dotshell_cameras.base import CameraBase

APIS = {"auto": cv2.CAP_ANY, "v4l2": cv2.CAP_V4L2, "ffmpeg": cv2.CAP_FFMPEG,
        "gstreamer": cv2.CAP_GSTREAMER, "images": cv2.CAP_IMAGES, "dshow": cv2.CAP_DSHOW,
        "msmf": cv2.CAP_MSMF}

SETTINGS_SCHEMA: dict[str, Setting] = {
    "source": Setting("str", "0", "camera index (\"0\"), device path (/dev/video2), video file, "
                      "image sequence (frames/%03d.png) or URL; files relative to the profile"),
    "api": Setting("str", "auto", "OpenCV capture API", choices=tuple(APIS)),
    "width": Setting("int", 0, "frame width to ask for; 0 = the driver's", "px", min=0),
    "height": Setting("int", 0, "frame height to ask for; 0 = the driver's", "px", min=0),
    "pixel_format": Setting("str", "", "FOURCC to ask for (GREY, Y16, YUYV, MJPG); empty = "
                            "the driver's"),
    "bit_depth": Setting("int", 8, "bits of the frames: 8, or 10–16 for Y16-style sources "
                         "(frames are uint16 then)", "bit", min=8, max=16),
    "gain": Setting("float", -1.0, "CAP_PROP_GAIN in the driver's units; -1 = leave it",
                    min=-1.0),
    "auto_exposure": Setting("bool", False, "leave auto exposure on (off: exposure_ms rules)"),
    "buffer_size": Setting("int", 1, "frames the driver may queue (CAP_PROP_BUFFERSIZE)",
                           min=1),
    "flush_frames": Setting("int", -1, "frames grabbed and dropped before each capture; -1 = "
                            "buffer_size for cameras, 0 for files", min=-1),
    "read_timeout_ms": Setting("int", 2000, "a capture that takes longer fails", "ms", min=1),
}


def v4l2_exposure(ms: float) -> float:
    """V4L2_CID_EXPOSURE_ABSOLUTE value (100 µs units) for ``ms`` milliseconds."""
    return max(1.0, round(ms * 10.0))


def log2_exposure(ms: float) -> float:
    """DirectShow / Media Foundation exposure value (log2 seconds) nearest ``ms``."""
    return float(round(math.log2(ms / 1000.0)))


def _is_file_source(source: str, api: str) -> bool:
    return api in ("ffmpeg", "images") or "%" in source or "://" in source or (
        not source.isdigit() and not source.startswith("/dev/"))


class OpenCVCamera(CameraBase):
    """Camera, ExposureControl, FrameInfoSource and Identified over ``cv2.VideoCapture``.

    ``opener(source, api, params) -> VideoCapture-like`` is for tests of the control logic."""

    def __init__(self, settings: dict[str, Any], base_dir: str = ".", opener=None) -> None:
        super().__init__(settings, (settings["width"], settings["height"]))
        src = settings["source"]
        self.is_file = _is_file_source(src, settings["api"])
        if self.is_file and "://" not in src and not Path(src).is_absolute():
            src = str(Path(base_dir) / src)
        self.source = src
        self.opener = opener or (lambda s, api, params: cv2.VideoCapture(
            int(s) if s.isdigit() else s, api, params))
        self.cap: Any = None
        self.frames = 0
        self._pool: ThreadPoolExecutor | None = None
        self._stuck = False

    # ---- Device ------------------------------------------------------------------------------

    @property
    def api_name(self) -> str:
        try:
            return self.cap.getBackendName().lower()
        except Exception:
            return self.settings["api"]

    def connect(self) -> None:
        s = self.settings
        # >8-bit frames must reach us undecoded: asked at open (FFmpeg decides it there)
        params = [cv2.CAP_PROP_CONVERT_RGB, 0] if s["bit_depth"] > 8 else []
        cap = self.opener(self.source, APIS[s["api"]], params)
        if cap is None or not cap.isOpened():
            what = "file" if self.is_file else "camera"
            raise DeviceError(f"opencv camera: cannot open {what} {self.source!r} with API "
                              f"{s['api']!r}; check the source (v4l2-ctl --list-devices for "
                              "cameras) and that no other program holds it.")
        self.cap = cap
        self.refused = {}
        self._stuck = False
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="dotshell-opencv")
        if s["pixel_format"]:
            code = cv2.VideoWriter_fourcc(*s["pixel_format"].ljust(4)[:4])
            self._control("pixel_format", cv2.CAP_PROP_FOURCC, code, exact=True)
        for key, prop in (("width", cv2.CAP_PROP_FRAME_WIDTH),
                          ("height", cv2.CAP_PROP_FRAME_HEIGHT)):
            if s[key]:
                self._control(key, prop, s[key], exact=True)
        if not self.is_file:
            self._control("buffer_size", cv2.CAP_PROP_BUFFERSIZE, s["buffer_size"], exact=True)
            if s["gain"] >= 0:
                self._control("gain", cv2.CAP_PROP_GAIN, s["gain"])
        self.size = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
                     int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))

    def close(self) -> None:
        if self.cap is not None:
            if not self._stuck:
                try:
                    self.cap.release()
                except Exception:  # closing must not raise
                    pass
            self.cap = None
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None

    def identity(self) -> DeviceIdentity:
        return DeviceIdentity(model=f"OpenCV {self.api_name} source {self.settings['source']}")

    def status(self) -> dict[str, Any]:
        return {"connected": self.cap is not None, "source": self.settings["source"],
                "api": self.api_name if self.cap is not None else self.settings["api"],
                "resolution": list(self.size), "exposure_ms": self.exposure_ms,
                "frames": self.frames, "refused_controls": dict(self.refused)}

    # ---- controls ----------------------------------------------------------------------------

    def _control(self, name: str, prop: int, value: float, exact: bool = False,
                 tolerance: float = 0.0) -> bool:
        """Set a property and read it back; record a refusal. True if it took."""
        ok = bool(self.cap.set(prop, value))
        got = self.cap.get(prop)
        if not ok:
            self.refused[name] = f"the {self.api_name} driver refused {value!r}"
            return False
        if (exact or tolerance) and not (abs(got - value) <= tolerance):
            self.refused[name] = f"asked {value!r}, the {self.api_name} driver kept {got!r}"
            return False
        self.refused.pop(name, None)
        return True

    def set_exposure(self, ms: float) -> None:
        if self.cap is None:
            raise DeviceError("opencv camera: not connected; connect the rig first.")
        if not (isinstance(ms, (int, float)) and math.isfinite(ms) and ms > 0):
            raise DeviceError(f"opencv camera: exposure must be a positive number of ms, got "
                              f"{ms!r}.")
        if self.is_file:
            self.refused["exposure_ms"] = ("the source is a recording (file, image sequence "
                                           "or stream): its exposure was fixed when recorded")
            return
        api = self.api_name
        if self.settings["auto_exposure"]:
            self.refused["exposure_ms"] = "auto_exposure = true leaves the exposure to the camera"
            return
        if "v4l2" in api:
            self._control("auto_exposure", cv2.CAP_PROP_AUTO_EXPOSURE, 1, exact=True)
            value = v4l2_exposure(ms)
            if self._control("exposure_ms", cv2.CAP_PROP_EXPOSURE, value, tolerance=0.5):
                self.exposure_ms = value / 10.0
        elif "dshow" in api or "msmf" in api:
            self._control("auto_exposure", cv2.CAP_PROP_AUTO_EXPOSURE, 0.25)
            value = log2_exposure(ms)
            if self._control("exposure_ms", cv2.CAP_PROP_EXPOSURE, value, tolerance=0.5):
                self.exposure_ms = 1000.0 * 2.0 ** value
        else:
            self.refused["exposure_ms"] = (f"no known exposure unit for the {api} capture API; "
                                           "set it with the camera's own tool")

    # ---- frames ------------------------------------------------------------------------------

    def _read(self, grab_only: bool = False) -> Any:
        if self.cap is None:
            raise DeviceError("opencv camera: not connected; connect the rig first.")
        if self._stuck:
            raise DeviceLostError("opencv camera: a read never returned; reopen the camera.")
        timeout = self.settings["read_timeout_ms"] / 1000.0
        job = self._pool.submit(self.cap.grab if grab_only else self.cap.read)
        try:
            return job.result(timeout=timeout)
        except FutureTimeout:
            self._stuck = True
            raise DeviceTimeout(f"opencv camera: no frame from {self.settings['source']!r} "
                                f"within {self.settings['read_timeout_ms']} ms.") from None

    def capture(self) -> np.ndarray:
        flush = self.settings["flush_frames"]
        if flush < 0:
            flush = 0 if self.is_file else self.settings["buffer_size"]
        for _ in range(flush):
            self._read(grab_only=True)
        t = time.time()
        ok, frame = self._read()
        if not ok or frame is None:
            if self.is_file:
                raise DeviceError(f"opencv camera: {self.source!r} has no frame {self.frames} "
                                  "(end of the recording); it holds fewer frames than the scan "
                                  "takes.")
            raise DeviceError(f"opencv camera: the driver returned no frame from "
                              f"{self.source!r}.")
        image = self._mono(frame)
        pos_ms = float(self.cap.get(cv2.CAP_PROP_POS_MSEC))
        self._info = FrameInfo(timestamp_s=t, frame_id=self.frames,
                               exposure_ms=self.exposure_ms, extra={"position_ms": pos_ms})
        self.frames += 1
        self.size = (image.shape[1], image.shape[0])
        return image

    def _mono(self, frame: np.ndarray) -> np.ndarray:
        f = np.asarray(frame)
        if f.ndim == 3 and f.shape[2] == 1:
            f = f[..., 0]
        elif f.ndim == 3:
            f = cv2.cvtColor(f, cv2.COLOR_BGRA2GRAY if f.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
        if self.settings["bit_depth"] > 8:
            return f.astype(np.uint16) if f.dtype != np.uint16 else f
        if f.dtype != np.uint8:
            raise DeviceError(f"opencv camera: frames are {f.dtype}; set bit_depth to the "
                              "source's bits (e.g. 16 for Y16).")
        return np.ascontiguousarray(f)
