"""The device conformance kit (dotshell.testing): every first-party backend passes it, and
deliberately broken drivers fail with the rule they break named."""

import threading
import time

import numpy as np
import pytest

from dotshell import hookimpl
from dotshell.backends import Backend, RigContext
from dotshell.errors import DeviceError
from dotshell.plugins import PluginManager
from dotshell.testing import assert_device_conforms, check_device

SMALL_CAMERA = {"width": 64, "height": 48, "focal_px": 320.0, "supersample": 1}


def sim_context(pm):
    """A rig context whose sim world has the projector and turntable a sim camera looks at."""
    ctx = RigContext()
    for role, name, settings in (("projector", "sim-projector",
                                  {"width": 64, "height": 48, "focal_px": 280.0}),
                                 ("stage", "sim-turntable", {})):
        pm.create(role, name, settings, ctx.for_device(role, name)).connect()
    return ctx


@pytest.mark.parametrize("role,name,settings", [
    ("projector", "sim-projector", {"width": 64, "height": 48}),
    ("stage", "sim-turntable", {}),
    ("analyzer", "sim-analyzer", {}),
    ("light_source", "sim-laser", {}),
])
def test_simulator_backends_conform(dotshell_pm, role, name, settings):
    assert_device_conforms(dotshell_pm, role, name, settings)


def test_sim_camera_conforms(dotshell_pm):
    assert_device_conforms(dotshell_pm, "camera", "sim-camera", SMALL_CAMERA,
                           context=sim_context(dotshell_pm))


@pytest.mark.parametrize("emulator,role,name", [
    ("grbl", "stage", "grbl"), ("zaber", "stage", "zaber"), ("apt", "stage", "thorlabs-apt"),
    ("elliptec", "analyzer", "elliptec"), ("switch", "light_source", "serial-switch"),
])
def test_serial_backends_conform_on_their_emulators(dotshell_pm, serial_emulator, emulator, role,
                                                    name):
    emu = serial_emulator(emulator)
    results = check_device(dotshell_pm, role, name, {"port": emu.port},
                           failing_settings={"port": "/nonexistent/ttyUSB9"})
    assert [str(r) for r in results if not r.passed] == []
    checked = {r.rule for r in results}
    assert {"failed-connect", "close-after-failed-connect", "connect-close-twice",
            "status-cheap", "raises-device-errors"} - checked <= {"raises-device-errors"}
    if role != "light_source":
        assert {"stop-interrupts-move", "stop-returns-fast", "home", "read-angle",
                "identity"} <= checked


# ---- deliberately broken drivers ------------------------------------------------------------

class Base:
    """A correct little device the broken ones start from."""

    def __init__(self, settings=None, context=None):
        self.connected = False
        self._angle = 0.0

    def connect(self):
        self.connected = True

    def close(self):
        self.connected = False

    def status(self):
        return {"connected": self.connected}

    def _need(self):
        if not self.connected:
            raise DeviceError("not connected; connect first")


class GoodCamera(Base):
    resolution = (16, 12)
    bit_depth = 12

    def capture(self):
        self._need()
        return np.full((12, 16), 100, np.uint16)


class GoodStage(Base):
    @property
    def position(self):
        return self._angle

    def move_to(self, degrees):
        self._need()
        if not np.isfinite(degrees):
            raise DeviceError("angle must be finite")
        self._angle = float(degrees)


class FloatRgbCamera(GoodCamera):  # a 10x10x3 float64 frame from a 12-bit declaration
    def capture(self):
        self._need()
        return np.random.default_rng(0).random((10, 10, 3))


class PortTouchingCamera(GoodCamera):  # a property that needs the hardware
    @property
    def resolution(self):
        if not self.connected:
            raise DeviceError("resolution unknown (not connected)")
        return (16, 12)


class OverRangeCamera(GoodCamera):  # 12-bit declared, 16-bit values
    def capture(self):
        self._need()
        return np.full((12, 16), 60000, np.uint16)


class ValueErrorStage(GoodStage):  # a plain exception instead of a DeviceError
    def move_to(self, degrees):
        self._need()
        if not np.isfinite(degrees):
            raise ValueError("cannot convert float NaN to integer")
        self._angle = float(degrees)


class CloseAfterFailStage(GoodStage):  # close() assumes connect() succeeded
    def connect(self):
        self.port = None
        raise DeviceError("no such port")

    def close(self):
        self.port.close()


class ReconnectRefusingStage(GoodStage):  # cannot connect again after close()
    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.used = False

    def connect(self):
        if self.used:
            raise DeviceError("port already in use")
        self.used = True
        self.connected = True


#: how fast the slow movers turn (degrees/s), how far the stop check moves them (degrees: a
#: 0.8 s move, stopped after 0.1 s) and how soon a stopped move must return (seconds): a
#: deaf stop's move still runs 0.4 s after that, a locked stop() blocks 0.7 s (> 0.2 s), a
#: correct stop returns within ~10 ms
SLOW_DEG_S = 200.0
STOP_MOVE_DEG = 160.0
STOP_WITHIN_S = 0.3


class SlowMover(GoodStage):
    """Moves at SLOW_DEG_S; stop() sets a flag the move honours."""

    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.lock = threading.Lock()
        self.halt = threading.Event()

    def move_to(self, degrees):
        self._need()
        if not np.isfinite(degrees):
            raise DeviceError("angle must be finite")
        self.halt.clear()
        with self.lock:
            start, t0 = self._angle, time.monotonic()
            while abs(self._angle - degrees) > 1e-9:
                if self.halt.is_set():
                    raise DeviceError("stopped")
                step = SLOW_DEG_S * (time.monotonic() - t0)
                self._angle = degrees if step >= abs(degrees - start) else start + step
                time.sleep(0.01)

    def stop(self):
        self.halt.set()


class LockedStop(SlowMover):  # stop() waits for the lock the move holds
    def stop(self):
        with self.lock:
            self.halt.set()


class DeafStop(SlowMover):  # stop() that the move never notices
    def stop(self):
        pass


class SlowStatus(GoodStage):  # status() queries the hardware (once connected), slowly
    def status(self):
        if self.connected:
            time.sleep(0.6)  # > STATUS_BUDGET_S (0.5 s) however fast the machine
        return {"connected": self.connected}


class NoStatusStage:  # misses a protocol member
    position = 0.0

    def __init__(self, settings=None, context=None):
        pass

    def connect(self):
        pass

    def close(self):
        pass

    def move_to(self, degrees):
        pass


class AttributeErrorCamera(GoodCamera):  # capture before connect fails with AttributeError
    def capture(self):
        return self.frame_buffer.copy()


class StuckStage(GoodStage):  # move_to returns but the stage never gets there
    def move_to(self, degrees):
        self._need()
        if not np.isfinite(degrees):
            raise DeviceError("angle must be finite")


class ObjectStatusCamera(GoodCamera):  # status() not JSON-serialisable
    def status(self):
        return {"connected": self.connected, "handle": object()}


BROKEN = {
    ("camera", "float-rgb"): (FloatRgbCamera, {"capture-shape", "capture-dtype"}),
    ("camera", "port-touching"): (PortTouchingCamera, {"properties-hardware-free"}),
    ("camera", "over-range"): (OverRangeCamera, {"capture-bit-depth"}),
    ("camera", "attribute-error"): (AttributeErrorCamera, {"raises-device-errors"}),
    ("camera", "object-status"): (ObjectStatusCamera, {"status-cheap"}),
    ("stage", "value-error"): (ValueErrorStage, {"raises-device-errors"}),
    ("stage", "close-after-fail"): (CloseAfterFailStage, {"close-after-failed-connect"}),
    ("stage", "reconnect-refusing"): (ReconnectRefusingStage, {"connect-close-twice"}),
    ("stage", "locked-stop"): (LockedStop, {"stop-returns-fast"}),
    ("stage", "deaf-stop"): (DeafStop, {"stop-interrupts-move"}),
    ("stage", "slow-status"): (SlowStatus, {"status-cheap"}),
    ("stage", "no-status"): (NoStatusStage, {"protocol-members"}),
    ("stage", "stuck"): (StuckStage, {"move-reaches-angle"}),
}


class BrokenPlugin:
    def _backends(self, role):
        return [Backend(name, cls, {}) for (r, name), (cls, _) in BROKEN.items() if r == role]

    @hookimpl
    def dotshell_cameras(self):
        return self._backends("camera") + [Backend("good", GoodCamera, {})]

    @hookimpl
    def dotshell_stages(self):
        return self._backends("stage") + [Backend("good", GoodStage, {}),
                                          Backend("slow-mover", SlowMover, {})]


@pytest.fixture
def broken_pm():
    pm = PluginManager()
    pm.register(BrokenPlugin(), name="broken-drivers")
    return pm


@pytest.mark.parametrize("role,name", [("camera", "good"), ("stage", "good"),
                                       ("stage", "slow-mover")])
def test_the_reference_drivers_pass(broken_pm, role, name):
    assert_device_conforms(broken_pm, role, name, move_deg=STOP_MOVE_DEG,
                           stop_within_s=STOP_WITHIN_S)


@pytest.mark.parametrize("role,name", sorted(BROKEN))
def test_broken_driver_fails_naming_the_rule(broken_pm, role, name):
    expected = BROKEN[(role, name)][1]
    failing = None if name != "close-after-fail" else {}
    results = check_device(broken_pm, role, name, failing_settings=failing,
                           move_deg=STOP_MOVE_DEG, stop_within_s=STOP_WITHIN_S)
    failed = {r.rule for r in results if not r.passed}
    assert expected <= failed, [str(r) for r in results]
    with pytest.raises(AssertionError, match=f"rule '{sorted(expected)[0]}'"):
        assert_device_conforms(broken_pm, role, name, failing_settings=failing,
                               move_deg=STOP_MOVE_DEG, stop_within_s=STOP_WITHIN_S)


def test_at_least_eight_broken_drivers_are_caught():
    assert len(BROKEN) >= 8 and len({rule for _, rules in BROKEN.values() for rule in rules}) >= 8
