"""One serial port as a driver uses it: opened by path, ``/dev/serial/by-id`` name or USB serial
number; every failure a :class:`~dotshell.errors.DeviceError` naming the device, the port, the
command and what would fix it.

* the port cannot be opened, or does not exist → :class:`DeviceError` (listing the ports there
  are);
* no complete reply within the reply timeout → :class:`DeviceTimeout`;
* the port fails under us (unplugged, powered off: ``EIO``, hang-up) → :class:`DeviceLostError`.

:meth:`SerialLink.write_now` writes without taking the link's lock, for ``stop()`` (from another
thread or a signal handler while a query waits for its reply).
"""

from __future__ import annotations

import threading
import time

import serial

try:
    from termios import error as TermiosError  # tcdrain on a vanished port (POSIX)
except ImportError:  # pragma: no cover - Windows
    TermiosError = OSError

from dotshell.errors import DeviceError, DeviceLostError, DeviceTimeout
from dotshell.rig.ports import resolve_port

#: What pyserial raises when the port fails under us (unplugged, closed from another thread).
PORT_FAILURES = (serial.SerialException, OSError, TermiosError, TypeError, AttributeError)


class SerialLink:
    """A serial port for one device.

    Args:
        device: how messages name the device, e.g. ``"grbl"``.
        port: path (``/dev/ttyUSB0``), ``by-id:NAME`` / a ``/dev/serial/by-id/...`` path, or
            ``serial:NUMBER`` (the USB serial number); see :func:`resolve_port`.
        baudrate: bits per second.
        reply_timeout_s: how long a reply may take (seconds).
        rtscts: hardware flow control.
    """

    def __init__(self, device: str, port: str, baudrate: int, reply_timeout_s: float,
                 rtscts: bool = False) -> None:
        self.device = device
        self.port_spec = port
        self.path = ""
        self.baudrate = baudrate
        self.reply_timeout_s = reply_timeout_s
        self.rtscts = rtscts
        self.serial: serial.Serial | None = None
        self.lock = threading.RLock()

    @property
    def name(self) -> str:
        """``device on PATH`` for messages."""
        return f"{self.device} on {self.path or self.port_spec}"

    @property
    def is_open(self) -> bool:
        s = self.serial
        return s is not None and s.is_open

    def open(self) -> None:
        """Open the port (8N1); a DeviceError with the ports present if it cannot be."""
        self.close()
        self.path = resolve_port(self.port_spec, self.device)
        try:
            self.serial = serial.serial_for_url(
                self.path, baudrate=self.baudrate, timeout=self.reply_timeout_s,
                write_timeout=self.reply_timeout_s, rtscts=self.rtscts, exclusive=True)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceError(
                f"{self.device}: cannot open {self.path} ({exc}). Is another program using it "
                "(close it), are you in the 'dialout' group, is the port right (run "
                "`dotshell ports`)?") from None

    def close(self) -> None:
        s, self.serial = self.serial, None
        if s is not None:
            try:
                s.close()
            except Exception:  # closing a vanished port
                pass

    def pulse_rts(self) -> bool:
        """Toggle RTS around an input/output purge (what FTDI-based controllers such as
        Thorlabs' expect after opening); False if the port has no modem lines (a pty)."""
        s = self._port("reset the port")
        try:
            s.rts = True
            s.reset_input_buffer()
            s.reset_output_buffer()
            time.sleep(0.05)
            s.rts = False
            return True
        except (OSError, TermiosError):
            s.reset_input_buffer()
            return False

    def _port(self, what: str) -> serial.Serial:
        s = self.serial
        if s is None or not s.is_open:
            raise DeviceError(f"{self.name}: cannot {what}: the port is not open; connect the "
                              "rig first.")
        return s

    def _lost(self, what: str, exc: BaseException) -> DeviceLostError:
        return DeviceLostError(f"{self.name}: the port failed while {what} ({exc}); the device "
                               "was unplugged, powered off or reset.")

    def write(self, data: bytes, what: str) -> None:
        """Write ``data`` (for ``what``, named in errors)."""
        with self.lock:
            self.write_now(data, what)

    def write_now(self, data: bytes, what: str = "stopping") -> None:
        """Write without the lock (``stop()``); raises like :meth:`write`."""
        s = self._port(what)
        try:
            s.write(data)
            s.flush()
        except serial.SerialTimeoutException:
            raise DeviceTimeout(f"{self.name}: could not send {what} within "
                                f"{self.reply_timeout_s:g} s (flow control stuck?)") from None
        except PORT_FAILURES as exc:
            raise self._lost(f"sending {what}", exc) from None

    def read_line(self, what: str, timeout_s: float | None = None,
                  newline: bytes = b"\n") -> str:
        """One reply line without its terminator (``\\r`` stripped too), decoded as ASCII;
        DeviceTimeout if none completes within ``timeout_s`` (default: the reply timeout)."""
        raw = self.read_until(newline, what, timeout_s)
        return raw.decode("ascii", errors="replace").strip("\r\n")

    def read_until(self, end: bytes, what: str, timeout_s: float | None = None) -> bytes:
        s = self._port(what)
        t = self.reply_timeout_s if timeout_s is None else timeout_s
        try:
            s.timeout = max(t, 0.0)
            raw = s.read_until(end)
        except PORT_FAILURES as exc:
            raise self._lost(f"waiting for the reply to {what}", exc) from None
        if not raw.endswith(end):
            raise self._silent(what, t, raw)
        return raw

    def _silent(self, what: str, timeout_s: float, partial: bytes) -> DeviceTimeout:
        got = f" (got only {partial[:40]!r})" if partial else ""
        return DeviceTimeout(
            f"{self.name}: no reply to {what} within {timeout_s:g} s{got}. Check that the "
            f"device is powered and connected, and that it talks at {self.baudrate} baud.")

    def discard_input(self) -> bytes:
        """Read and drop whatever is waiting (stale replies, noise); returns it."""
        s = self._port("clear the input")
        try:
            waiting = s.in_waiting
            return s.read(waiting) if waiting else b""
        except PORT_FAILURES as exc:
            raise self._lost("clearing the input", exc) from None
