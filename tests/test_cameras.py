"""Camera drivers: OpenCV control mapping, refusals and read timeouts (against a stand-in
VideoCapture; real files are replayed in test_hardware_scans.py); GenICam through the real
harvesters package (messages without a producer) and a stand-in acquirer; pylablib scientific
cameras against a stand-in implementing pylablib's documented camera interface."""

from __future__ import annotations

import sys
import threading
import time
from collections import namedtuple

import cv2
import numpy as np
import pytest

from dotshell.errors import DeviceError, DeviceLostError, DeviceTimeout
from dotshell.settings import validate_settings
from dotshell_cameras.genicam import SETTINGS_SCHEMA as GENICAM_SCHEMA
from dotshell_cameras.genicam import GenICamCamera
from dotshell_cameras.opencv import SETTINGS_SCHEMA as OPENCV_SCHEMA
from dotshell_cameras.opencv import OpenCVCamera, log2_exposure, v4l2_exposure
from dotshell_cameras.scientific import SETTINGS_SCHEMA as SCIENTIFIC_SCHEMA
from dotshell_cameras.scientific import ScientificCamera


# ---- OpenCV ----------------------------------------------------------------------------------

class StandInCapture:
    """cv2.VideoCapture's set/get/read/grab as a V4L2 driver answers them; ``ignores`` are
    properties the driver accepts but does not change, ``refuses`` ones whose set() fails."""

    def __init__(self, backend="V4L2", ignores=(), refuses=(), block=None):
        self.props = {cv2.CAP_PROP_FRAME_WIDTH: 64, cv2.CAP_PROP_FRAME_HEIGHT: 48}
        self.backend, self.ignores, self.refuses, self.block = backend, ignores, refuses, block
        self.reads = 0

    def isOpened(self):
        return True

    def getBackendName(self):
        return self.backend

    def set(self, prop, value):
        if prop in self.refuses:
            return False
        if prop not in self.ignores:
            self.props[prop] = float(value)
        return True

    def get(self, prop):
        return self.props.get(prop, 0.0)

    def grab(self):
        return True

    def read(self):
        if self.block is not None:
            self.block.wait()
        self.reads += 1
        return True, np.full((48, 64, 3), self.reads, np.uint8)

    def release(self):
        pass


def _opencv(cap, **settings):
    cam = OpenCVCamera(validate_settings(OPENCV_SCHEMA, {"source": "/dev/video0",
                                                         **settings}, "opencv"),
                       opener=lambda s, api, params: cap)
    cam.connect()
    return cam


def test_exposure_units_per_capture_api():
    assert v4l2_exposure(20.0) == 200.0          # 100 µs units
    assert log2_exposure(31.25) == -5.0           # log2 seconds
    cap = StandInCapture()
    cam = _opencv(cap)
    cam.set_exposure(20.0)
    assert cap.props[cv2.CAP_PROP_AUTO_EXPOSURE] == 1.0  # V4L2_EXPOSURE_MANUAL
    assert cap.props[cv2.CAP_PROP_EXPOSURE] == 200.0 and cam.exposure_ms == 20.0
    assert cap.props[cv2.CAP_PROP_BUFFERSIZE] == 1.0
    frame = cam.capture()
    assert frame.shape == (48, 64) and frame.dtype == np.uint8
    assert cap.reads == 1 and cam.status()["refused_controls"] == {}


def test_refused_and_ignored_controls_are_reported():
    cap = StandInCapture(ignores={cv2.CAP_PROP_EXPOSURE}, refuses={cv2.CAP_PROP_GAIN})
    cam = _opencv(cap, gain=4.0)
    cam.set_exposure(20.0)
    refused = cam.status()["refused_controls"]
    assert refused["gain"] == "the v4l2 driver refused 4.0"
    assert refused["exposure_ms"] == "asked 200, the v4l2 driver kept 0.0"


def test_a_hung_read_times_out_and_the_camera_is_reported_lost():
    gate = threading.Event()
    cam = _opencv(StandInCapture(block=gate), read_timeout_ms=200, flush_frames=0)
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match="within 200 ms"):
        cam.capture()
    assert time.monotonic() - t0 < 1.0
    with pytest.raises(DeviceLostError, match="reopen"):
        cam.capture()
    gate.set()
    cam.close()


# ---- GenICam ---------------------------------------------------------------------------------

def test_genicam_without_the_extra_names_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "harvesters.core", None)
    cam = GenICamCamera(validate_settings(GENICAM_SCHEMA, {}, "genicam"))
    with pytest.raises(DeviceError, match=r"pip install 'dotshell\[genicam\]'"):
        cam.connect()


def test_genicam_with_real_harvesters_and_no_producer(tmp_path, monkeypatch):
    pytest.importorskip("harvesters.core")
    monkeypatch.delenv("GENICAM_GENTL64_PATH", raising=False)
    cam = GenICamCamera(validate_settings(GENICAM_SCHEMA, {}, "genicam"))
    with pytest.raises(DeviceError, match="no GenTL producer configured"):
        cam.connect()
    cam = GenICamCamera(validate_settings(GENICAM_SCHEMA, {"cti": [str(tmp_path / "x.cti")]},
                                          "genicam"))
    with pytest.raises(DeviceError, match="x.cti does not exist"):
        cam.connect()


class Node:
    def __init__(self, value=None, allowed=None, on_execute=None):
        self._value, self.allowed, self.on_execute = value, allowed, on_execute

    @property
    def value(self):
        return self._value

    @value.setter
    def value(self, v):
        if self.allowed is not None and v not in self.allowed:
            raise ValueError(f"{v!r} is not an enumeration entry")
        self._value = v

    def execute(self):
        self.on_execute()


class StandInAcquirer:
    """harvesters' ImageAcquirer as a camera with a trigger input answers it."""

    def __init__(self):
        self.delivered = []
        self.frames = 0
        n = self
        self.remote_device = type("Remote", (), {})()
        nodes = dict(DeviceModelName=Node("acA1300-60gm"), DeviceSerialNumber=Node("2211"),
                     DeviceFirmwareVersion=Node("1.2"), DeviceVendorName=Node("Basler"),
                     PixelFormat=Node("Mono8", {"Mono8", "Mono12"}), ExposureAuto=Node("Off"),
                     ExposureTime=Node(1000.0), TriggerSelector=Node("FrameStart"),
                     TriggerMode=Node("Off"), TriggerSource=Node("Software",
                                                                 {"Software", "Line1"}),
                     TriggerActivation=Node("RisingEdge"), Width=Node(64), Height=Node(48),
                     SensorReadoutTime=Node(16000.0),
                     TriggerSoftware=Node(on_execute=lambda: n.edge()))
        self.remote_device.node_map = type("NodeMap", (), nodes)()

    def edge(self):
        self.frames += 1
        self.delivered.append(self.frames)

    def start(self):
        pass

    def stop(self):
        pass

    def destroy(self):
        pass

    def try_fetch(self, timeout=0.0):
        return self._buffer() if self.delivered else None

    def fetch(self, timeout=0.0):
        from genicam.gentl import TimeoutException

        if not self.delivered:
            raise TimeoutException()
        return self._buffer()

    def _buffer(self):
        k = self.delivered.pop(0)
        comp = type("C", (), dict(data=np.full(48 * 64, k, np.uint16), width=64, height=48))
        return type("B", (), dict(payload=type("P", (), {"components": [comp]}),
                                  timestamp_ns=k * 1_000_000, frame_id=k,
                                  queue=lambda self: None))()


class StandInHarvester:
    def __init__(self, acquirer):
        self.acquirer, self.files = acquirer, []
        self.device_info_list = [{"serial_number": "2211"}]

    def add_file(self, f):
        self.files.append(f)

    def update(self):
        pass

    def create(self, key):
        return self.acquirer

    def reset(self):
        pass


def test_genicam_controls_software_and_hardware_trigger(tmp_path):
    pytest.importorskip("genicam.gentl")
    cti = tmp_path / "producer.cti"
    cti.write_bytes(b"")
    ia = StandInAcquirer()
    cam = GenICamCamera(validate_settings(GENICAM_SCHEMA, {"cti": [str(cti)], "gain_db": 6.0},
                                          "genicam"),
                        harvester_factory=lambda: StandInHarvester(ia))
    cam.connect()
    nodes = ia.remote_device.node_map
    assert cam.identity().model == "acA1300-60gm" and nodes.PixelFormat.value == "Mono12"
    assert nodes.TriggerMode.value == "On" and nodes.TriggerSource.value == "Software"
    assert "gain_db" in cam.status()["refused_controls"]  # this camera has no Gain feature
    cam.set_exposure(20.0)
    assert nodes.ExposureTime.value == 20000.0 and cam.min_trigger_period_ms(20.0) == 36.0
    ia.delivered.append(99)  # a stale frame delivered before the call is dropped
    frame = cam.capture()
    assert frame.dtype == np.uint16 and frame[0, 0] == 1
    cam.arm(3, 20.0)
    assert nodes.TriggerSource.value == "Line1"
    for _ in range(2):
        ia.edge()
    with pytest.raises(DeviceTimeout, match="2 of 3 triggered frames.*Line1"):
        cam.read_armed(0.05)
    cam.arm(2, 20.0)
    ia.edge(), ia.edge()
    got = cam.read_armed(0.05)
    assert [f[0, 0] for f, _ in got] == [4, 5] and got[1][1].frame_id == 5
    cam.disarm()
    assert nodes.TriggerSource.value == "Software"
    cam.close()


# ---- pylablib scientific cameras ------------------------------------------------------------

class StandInScientific:
    """The documented pylablib camera interface (ICamera / IExposureCamera / IBinROICamera and
    Andor's EM gain and cooling calls), as an EMCCD with a 512 × 512 sensor answers it."""

    TimeoutError = type("StandInTimeoutError", (Exception,), {})
    TFrameInfo = namedtuple("TFrameInfo", "frame_index timestamp_dev")
    TDeviceInfo = namedtuple("TDeviceInfo", "controller_model head_model serial_number")

    def __init__(self, idx):
        self.opened, self.exposure, self.roi = False, 0.01, (0, 512, 0, 512, 1, 1)
        self.trigger, self.em_gain, self.temperature = "int", 0, 20.0
        self.buffer, self.acquiring, self.index = [], False, 0

    def open(self):
        self.opened = True

    def close(self):
        self.opened = False

    def is_opened(self):
        return self.opened

    def get_device_info(self):
        return self.TDeviceInfo("USB", "DU897_BV", 4242)

    def set_exposure(self, exposure):
        self.exposure = exposure

    def get_exposure(self):
        return self.exposure

    def get_frame_timings(self):
        return (self.exposure, self.exposure + 0.0305)  # EMCCD frame transfer + readout

    def get_detector_size(self):
        return (512, 512)

    def set_roi(self, hstart=0, hend=None, vstart=0, vend=None, hbin=1, vbin=1):
        self.roi = (hstart, hend, vstart, vend, hbin, vbin)

    def get_data_dimensions(self):
        h0, h1, v0, v1, hb, vb = self.roi
        return ((v1 - v0) // vb, (h1 - h0) // hb)

    def set_trigger_mode(self, mode):
        if mode not in ("int", "ext", "software"):
            raise ValueError(f"unknown trigger mode {mode}")
        self.trigger = mode

    def set_EMCCD_gain(self, gain, advanced=None):
        self.em_gain = gain

    def set_temperature(self, temperature, enable_cooler=True):
        self.temperature = temperature

    def get_temperature(self):
        return self.temperature + 0.5

    def get_temperature_status(self):
        return "stabilized"

    def _frame(self):
        self.index += 1
        rows, cols = self.get_data_dimensions()
        return np.full((rows, cols), self.index, np.uint16), self.TFrameInfo(self.index,
                                                                             0.001 * self.index)

    def snap(self, timeout=5.0, return_info=False):
        frame, info = self._frame()
        return (frame, info) if return_info else frame

    def start_acquisition(self, mode="sequence", nframes=None):
        self.acquiring, self.buffer = True, []

    def stop_acquisition(self):
        self.acquiring = False

    def wait_for_frame(self, since="lastread", nframes=1, timeout=20.0, error_on_stopped=False):
        if len(self.buffer) < nframes:
            raise self.TimeoutError()

    def read_multiple_images(self, rng=None, peek=False, missing_frame="skip",
                             return_info=False, return_rng=False):
        frames, self.buffer = self.buffer, []
        return [f for f, _ in frames], [i for _, i in frames]

    def trigger_in(self):  # an edge on the external trigger input
        if self.acquiring and self.trigger == "ext":
            self.buffer.append(self._frame())


def test_scientific_camera_roi_binning_gain_cooling_and_triggers():
    stand_in = StandInScientific(0)
    cam = ScientificCamera(validate_settings(SCIENTIFIC_SCHEMA, {
        "roi": [0, 512, 128, 384], "binning": [2, 2], "em_gain": 200, "temperature_c": -60.0},
        "scientific"), camera_factory=lambda idx: stand_in)
    cam.connect()
    assert cam.resolution == (256, 128) and stand_in.em_gain == 200
    assert cam.identity().serial_number == "4242"
    status = cam.status()
    assert status["temperature_c"] == -59.5 and status["cooling"] == "stabilized"
    cam.set_exposure(20.0)
    assert stand_in.exposure == pytest.approx(0.02)
    assert cam.min_trigger_period_ms(20.0) == pytest.approx(50.5)
    frame = cam.capture()
    assert frame.shape == (128, 256) and cam.last_frame_info().frame_id == 1
    cam.arm(3, 20.0)
    assert stand_in.trigger == "ext"
    stand_in.trigger_in()
    with pytest.raises(DeviceTimeout, match="1 of 3 triggered frames"):
        cam.read_armed(0.01)
    cam.arm(2, 20.0)
    stand_in.trigger_in(), stand_in.trigger_in()
    got = cam.read_armed(0.01)
    assert [i.frame_id for _, i in got] == [3, 4] and got[0][1].timestamp_s == pytest.approx(0.003)
    cam.disarm()
    assert stand_in.trigger == "int" and not stand_in.acquiring
    cam.close()


def test_scientific_camera_refusals_are_named():
    stand_in = StandInScientific(0)
    cam = ScientificCamera(validate_settings(SCIENTIFIC_SCHEMA, {"external_trigger": "bulb"},
                                             "scientific"), camera_factory=lambda idx: stand_in)
    cam.connect()
    with pytest.raises(DeviceError, match="trigger mode 'bulb' refused"):
        cam.arm(2, 20.0)
