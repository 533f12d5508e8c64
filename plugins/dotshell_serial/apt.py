"""Thorlabs APT / Kinesis rotation mounts over their FTDI serial port (K10CR1 class).

Protocol: Thorlabs "APT Communications Protocol" (Issue 37+, thorlabs.com, Motion Control
software docs). Messages are a 6-byte header (message id, two parameters or a data length,
destination, source) plus data for long messages; the host is 0x01, a stand-alone USB
controller 0x50. Used here: HW_NO_FLASH_PROGRAMMING (0x0018), HW_REQ_INFO/GET_INFO (0x0005/6),
MOD_SET_CHANENABLESTATE (0x0210), MOT_MOVE_HOME/HOMED (0x0443/4), MOT_MOVE_ABSOLUTE (0x0453) →
MOT_MOVE_COMPLETED (0x0464), MOT_MOVE_STOP (0x0465) → MOT_MOVE_STOPPED (0x0466),
MOT_REQ/GET_STATUSUPDATE (0x0480/1), HW_RICHRESPONSE (0x0081, errors). Port: 115200 baud, 8N1,
RTS/CTS, RTS pulsed after opening. Positions are microsteps: the K10CR1 has 136533.33 per degree
(200 steps × 2048 microsteps × 120:1 worm gear / 360°).

Messages are packed and parsed with ``thorlabs-apt-protocol`` (MIT, the yaq project): a
well-tested, I/O-free implementation of exactly this framing; the I/O, timing, stop and error
handling are ours.
"""

from __future__ import annotations

import time
from functools import lru_cache
from types import ModuleType
from typing import Any

from dotshell.errors import DeviceError, DeviceTimeout
from dotshell.settings import Setting

from dotshell_serial.base import (MotionWatch, SerialDevice, finite_degrees, motion_settings,
                                  port_settings)

HOST = 0x01
#: Status bits of MOT_GET_STATUSUPDATE (APT protocol, "Status bits").
LIMIT_BITS = {0x01: "forward (CW) hardware limit", 0x02: "reverse (CCW) hardware limit",
              0x04: "forward software limit", 0x08: "reverse software limit"}

APT_SCHEMA: dict[str, Setting] = {
    **port_settings(115200, 1.0),
    **motion_settings(),
    "channel": Setting("int", 1, "motor channel", min=1, max=4),
    "destination": Setting("int", 0x50, "APT destination address: 80 (0x50) for a stand-alone "
                           "USB controller such as the K10CR1; 0x21.. for a rack bay",
                           min=0, max=255),
    "counts_per_degree": Setting("float", 136533.333333, "microsteps (encoder counts) per "
                                 "degree: K10CR1 136533.33; PRM1-Z8 1919.64", "1/deg", min=1.0),
    "tolerance_deg": Setting("float", 0.01, "how close the reported angle must come to the "
                             "target", "deg", min=0.0, max=5.0),
    "poll_interval_s": Setting("float", 0.1, "time between status requests while moving", "s",
                               min=0.01, max=1.0),
}


class _Overdue(DeviceTimeout):
    """The awaited message did not come before the deadline (the device kept answering)."""


def _apt() -> ModuleType:
    """thorlabs_apt_protocol, imported when a stage first talks (it imports asyncio: 0.1-0.2 s
    that every command loading the plugins paid)."""
    import thorlabs_apt_protocol

    return thorlabs_apt_protocol


@lru_cache(maxsize=1)
def _unpacker_class() -> type:
    class Unpacker(_apt().Unpacker):
        """The library's unpacker, counting the bytes it had to skip (line noise)."""

        skipped = 0

        def _decoding_error(self, message: str = "") -> None:
            self.skipped += 1
            super()._decoding_error(message)

    return Unpacker


class AptRotationStage(SerialDevice):
    """A Thorlabs APT rotation mount; Stage, Stoppable, Homing, AngleReadback, Identified."""

    model = "thorlabs-apt"
    rtscts = True

    def __init__(self, settings: dict[str, Any], context=None) -> None:
        super().__init__(settings, context)
        self._unpacker: Any = None  # _unpacker_class(), made at the first reply
        self.status_bits: dict[str, Any] = {}

    @property
    def _dest(self) -> int:
        return self.settings["destination"]

    @property
    def _chan(self) -> int:
        return self.settings["channel"]

    # ---- messages -------------------------------------------------------------------------------

    def _send(self, message: bytes, what: str) -> None:
        self.link.write(message, what)

    def _await(self, wanted: set[str], what: str, timeout_s: float | None = None,
               poll: bool = False, watch: MotionWatch | None = None) -> Any:
        """The next message named in ``wanted`` (thorlabs_apt_protocol names); errors from the
        controller raise; with ``poll`` a status request goes out every poll interval, and
        ``watch`` sees each position it reports (a stall is named)."""
        if self._unpacker is None:
            self._unpacker = _unpacker_class()(self.link._port(f"wait for {what}"),
                                               on_error="continue")
        t = self.link.reply_timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + t
        heard = time.monotonic()
        next_poll = 0.0
        while True:
            if self.stopping.is_set() and "mot_move_stopped" not in wanted:
                wanted = wanted | {"mot_move_stopped"}
            now = time.monotonic()
            if poll and now >= next_poll:
                self._send(_apt().mot_req_statusupdate(self._dest, HOST, self._chan),
                           "a status request")
                next_poll = now + self.settings["poll_interval_s"]
            port = self.link._port(f"wait for {what}")
            try:
                port.timeout = 0.02
                msg = next(self._unpacker, None)
            except Exception as exc:  # the unpacker reads the port: a vanished port fails here
                raise self.link._lost(f"waiting for {what}", exc) from None
            if self._unpacker.skipped:
                self._noise(f"{self._unpacker.skipped} bytes that are no APT message")
                self._unpacker.skipped = 0
            if msg is not None:
                heard = time.monotonic()
                self._note(msg)
                if watch is not None and msg.msg == "mot_get_statusupdate":
                    watch.update(self._position)
                if msg.msg in ("hw_richresponse", "hw_response"):
                    raise DeviceError(self._controller_error(msg, what))
                if msg.msg in wanted:
                    return msg
            elif poll and time.monotonic() - heard > self.link.reply_timeout_s:
                raise DeviceTimeout(f"{self.link.name}: no reply to the status requests "
                                    f"(MOT_REQ_STATUSUPDATE) during {what} within "
                                    f"{self.link.reply_timeout_s:g} s. Check that the controller "
                                    "is powered and connected.")
            elif time.monotonic() > deadline:
                raise _Overdue(f"{self.link.name}: no reply to {what} within {t:g} s. Check "
                                    "that the controller is powered and connected (and not "
                                    "held by the Kinesis software).")

    def _note(self, msg: Any) -> None:
        if msg.msg in ("mot_get_statusupdate", "mot_move_completed", "mot_move_stopped"):
            self._position = msg.position / self.settings["counts_per_degree"]
            self.status_bits = msg._asdict()

    def _controller_error(self, msg: Any, what: str) -> str:
        if msg.msg == "hw_richresponse":
            raw = msg.notes if isinstance(msg.notes, (bytes, bytearray)) else b"".join(
                n if isinstance(n, bytes) else bytes([n]) for n in msg.notes)
            notes = raw.split(b"\0")[0].decode("ascii", "replace").strip()
            text = notes or "no text"
            return (f"{self.link.name}: the controller reported error {msg.code} ({text}) about "
                    f"message 0x{msg.msg_ident:04x} during {what}; see the APT protocol's error "
                    "codes, fix the cause and reconnect.")
        return f"{self.link.name}: the controller reported an unspecified error during {what}."

    def _limits(self) -> list[str]:
        raw = 0
        for bit, name in ((0x01, "forward_limit_switch"), (0x02, "reverse_limit_switch")):
            raw |= bit if self.status_bits.get(name) else 0
        return [text for bit, text in LIMIT_BITS.items() if raw & bit]

    # ---- lifecycle ------------------------------------------------------------------------------

    def _handshake(self) -> None:
        self._unpacker = None
        self.link.pulse_rts()  # what Thorlabs asks for after opening; a pty has no RTS
        self._send(_apt().hw_no_flash_programming(self._dest, HOST), "HW_NO_FLASH_PROGRAMMING")
        self._send(_apt().hw_req_info(self._dest, HOST), "HW_REQ_INFO")
        info = self._await({"hw_get_info"}, "HW_REQ_INFO (identify)")
        fw = ".".join(str(v) for v in info.firmware_version)  # major, interim, minor
        self.ident = type(self.ident)(
            model=info.model_number.split(b"\0")[0].decode("ascii", "replace"),
            serial_number=str(info.serial_number), firmware=fw, vendor="Thorlabs")
        self._send(_apt().mod_set_chanenablestate(self._dest, HOST, self._chan, 1),
                   "MOD_SET_CHANENABLESTATE")
        self.read_angle()
        if not self.status_bits.get("homed"):
            self.context.log.warn(f"{self.ident.model} {self.ident.serial_number} is not homed: "
                                  "angles are relative to where it was powered on; set [stage] "
                                  "home = \"on_connect\" for absolute angles")

    # ---- role -----------------------------------------------------------------------------------

    def read_angle(self) -> float:
        self._send(_apt().mot_req_statusupdate(self._dest, HOST, self._chan),
                   "MOT_REQ_STATUSUPDATE")
        self._await({"mot_get_statusupdate"}, "MOT_REQ_STATUSUPDATE")
        return self._position

    def move_to(self, degrees: float) -> None:
        target = finite_degrees(degrees, self.link.name)
        self.stopping.clear()
        counts = round(target * self.settings["counts_per_degree"])
        self._send(_apt().mot_move_absolute(self._dest, HOST, self._chan, counts),
                   f"MOT_MOVE_ABSOLUTE to {target:g}°")
        self._finish(f"the move to {target:g}°", target)

    def home(self) -> None:
        self.stopping.clear()
        self._send(_apt().mot_move_home(self._dest, HOST, self._chan), "MOT_MOVE_HOME")
        self._finish("homing", None)

    def _finish(self, what: str, target: float | None) -> None:
        done = {"mot_move_completed"} if target is not None else {"mot_move_homed"}
        left = self.context.time_left()
        budget = 120.0 if left == float("inf") else max(left - 0.5, 0.1)
        try:
            msg = self._await(done | {"mot_move_stopped"}, what, budget, poll=True,
                              watch=MotionWatch(self, what, log_progress=target is None))
        except _Overdue:
            self.stop()
            raise DeviceTimeout(f"{self.link.name}: {what} did not finish in time (at "
                                f"{self._position:.3f}°); sent MOT_MOVE_STOP. Check the mount; "
                                "if it is just slow, raise [stage.timeouts] move_to.") from None
        if msg.msg == "mot_move_stopped":
            if self.stopping.is_set():
                raise self._stopped(self._position)
            limits = self._limits()
            raise DeviceError(f"{self.link.name}: the controller stopped {what} at "
                              f"{self._position:.3f}°"
                              + (f" ({', '.join(limits)})" if limits else "")
                              + "; clear the limit and home the mount.")
        if target is None:
            self.read_angle()
            return
        tol = self.settings["tolerance_deg"]
        if abs(self._position - target) > tol:
            raise DeviceError(f"{self.link.name}: {what} ended at {self._position:.3f}°, "
                              f"{abs(self._position - target):.3f}° off; check "
                              "counts_per_degree for this mount.")

    def stop(self) -> None:
        """MOT_MOVE_STOP (profiled), sent without the link's lock."""
        self.stopping.set()
        if self.link.is_open:
            try:
                self.link.write_now(_apt().mot_move_stop(self._dest, HOST, self._chan, 0x02),
                                    "MOT_MOVE_STOP")
            except DeviceError:
                pass

    def status(self) -> dict[str, Any]:
        out = super().status()
        if self.status_bits:
            out.update(homed=bool(self.status_bits.get("homed")), limits=self._limits())
        return out
