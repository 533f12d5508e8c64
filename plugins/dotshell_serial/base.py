"""What the serial drivers share: the port settings, connect/close around a handshake, a
hardware-free status, identity, and the stop flag ``stop()`` raises for the waiting call."""

from __future__ import annotations

import math
import threading
import time
from typing import Any

from dotshell.backends import RigContext
from dotshell.devices import DeviceIdentity
from dotshell.errors import DeviceError
from dotshell.settings import REQUIRED, Setting

from dotshell_serial.link import SerialLink


def port_settings(baudrate: int, reply_timeout_s: float) -> dict[str, Setting]:
    """The settings every serial backend has (port, baud rate, reply timeout)."""
    return {
        "port": Setting("str", REQUIRED, "serial port: a path (/dev/ttyUSB0, COM3), "
                        "by-id:NAME (/dev/serial/by-id, survives re-plugging) or serial:NUMBER "
                        "(the USB serial number); `dotshell ports` lists them"),
        "baudrate": Setting("int", baudrate, "bits per second (the device's default is "
                            f"{baudrate})", "baud", min=300, max=4_000_000),
        "reply_timeout_s": Setting("float", reply_timeout_s, "how long one reply may take",
                                   "s", min=0.01, max=60.0),
    }


def motion_settings() -> dict[str, Setting]:
    """The settings of backends that move (stall detection, homing progress)."""
    return {
        "stall_s": Setting("float", 3.0, "a move or homing that reports busy without moving "
                           "more than 0.005° for this long is stuck: stopped and named", "s",
                           min=0.2, max=600.0),
        "progress_s": Setting("float", 5.0, "how often homing logs where it is", "s",
                              min=0.5, max=600.0),
    }


class MotionWatch:
    """Watches one move or homing through the positions polled while it runs: names a stall
    (no progress for ``stall_s`` seconds) and logs homing progress every ``progress_s``."""

    #: Least change of position that counts as progress (degrees).
    PROGRESS_DEG = 0.005

    def __init__(self, device: SerialDevice, what: str, log_progress: bool = False) -> None:
        self.device, self.what, self.log_progress = device, what, log_progress
        now = time.monotonic()
        self.t_moved = self.t_logged = self.t0 = now
        self.at: float | None = None

    def update(self, position: float) -> None:
        """A position polled while busy; a DeviceError once it has not changed for
        ``stall_s`` (the device is stopped first)."""
        now = time.monotonic()
        settings = self.device.settings
        if self.at is None or abs(position - self.at) > self.PROGRESS_DEG:
            self.at, self.t_moved = position, now
        elif now - self.t_moved >= settings["stall_s"]:
            self.device.stop()
            self.device.stopping.clear()
            raise DeviceError(f"{self.device.link.name}: {self.what} is stuck — the device says "
                              f"it is moving but has stayed at {position:.3f}° for "
                              f"{now - self.t_moved:.1f} s; stopped it. Check what blocks the "
                              "stage (and its motor current); raise stall_s if it is just "
                              "slow to start.")
        if self.log_progress and now - self.t_logged >= settings["progress_s"]:
            self.t_logged = now
            left = self.device.context.time_left()
            deadline = "" if math.isinf(left) else f", {left:.0f} s left of its deadline"
            self.device.context.log.info(f"{self.what}: at {position:.2f}° after "
                                         f"{now - self.t0:.0f} s{deadline}")


def finite_degrees(value: Any, device: str) -> float:
    """``value`` as a finite float, or a DeviceError naming the device."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise DeviceError(f"{device}: the angle must be a finite number of degrees, got "
                          f"{value!r}.")
    return float(value)


class SerialDevice:
    """Base of the serial drivers. Subclasses implement :meth:`_handshake` (talk to the device
    after the port opened: check it is what we think, read identity) and their role's method.

    Properties are hardware-free (the contract): ``position`` is the last angle read back.
    """

    model = "serial device"
    rtscts = False

    def __init__(self, settings: dict[str, Any], context: RigContext | None = None) -> None:
        self.settings = settings
        self.context = context or RigContext()
        self.link = SerialLink(self.model, settings["port"], settings["baudrate"],
                               settings["reply_timeout_s"], rtscts=self.rtscts)
        self.ident = DeviceIdentity()
        self.stopping = threading.Event()
        self._position = 0.0
        self._state = "closed"
        self._noisy = False

    def connect(self) -> None:
        self._noisy = False
        self.link.open()
        try:
            self._handshake()
        except BaseException:
            self.link.close()
            raise
        self._state = "idle"

    def _handshake(self) -> None:
        raise NotImplementedError

    def close(self) -> None:
        self.link.close()
        self._state = "closed"

    @property
    def position(self) -> float:
        """Last angle read back from the device (degrees); hardware-free."""
        return self._position

    def identity(self) -> DeviceIdentity:
        return self.ident

    def status(self) -> dict[str, Any]:
        """Hardware-free: connection, port, state and the last angle read back."""
        return {"connected": self.link.is_open, "port": self.link.path or self.settings["port"],
                "state": self._state, "angle_deg": round(self._position, 4)}

    def _noise(self, junk: str) -> None:
        """Bytes that are no reply (line noise): warn once per connection, then carry on."""
        if junk.strip() and not self._noisy:
            self._noisy = True
            self.context.log.warn(f"noise on {self.link.path}: {junk[:24]!r} arrived where a "
                                  "reply was expected; replies are still understood. Check the "
                                  "cable, its shielding and ground, and the baud rate "
                                  f"({self.link.baudrate}).")

    def _stopped(self, where: float) -> DeviceError:
        self.stopping.clear()
        return DeviceError(f"{self.link.name}: stopped at {where:.3f}°.")
