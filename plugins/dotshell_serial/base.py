"""What the serial drivers share: the port settings, connect/close around a handshake, a
hardware-free status, identity, and the stop flag ``stop()`` raises for the waiting call."""

from __future__ import annotations

import math
import threading
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
