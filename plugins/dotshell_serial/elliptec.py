"""Thorlabs Elliptec rotation mounts (ELL14 / ELL18 class) as the polarization analyzer for PDI.

Protocol: Thorlabs "Elliptec ELLx modules communication protocol manual" (Issue 5+). 9600 baud
8N1, ASCII; the host sends ``<address><command>[data]`` with no terminator, lower-case commands;
the module answers upper-case ``<address><REPLY><data>\\r\\n``. Used: ``in`` → ``IN`` (model,
serial number, year, firmware, travel, pulses per unit), ``gs`` → ``GS`` (status code), ``gp`` →
``PO`` (position), ``ma<8 hex>`` move absolute → ``PO`` when done (or ``GS`` + error code),
``ho0`` home clockwise → ``PO``, ``st`` stop. Positions are 32-bit two's-complement hex pulses;
an ELL14 has 143360 pulses per 360°.

The analyzer angle is the mount angle minus ``offset_deg`` (the mount angle at which the
analyzer's axis is parallel to the projector's polarizer).
"""

from __future__ import annotations

import re
from typing import Any

from dotshell.errors import DeviceError, DeviceTimeout
from dotshell.settings import Setting

from dotshell_serial.base import SerialDevice, finite_degrees, port_settings

#: Module status codes (``GS`` replies), from the protocol manual.
STATUS = {0: "ok", 1: "communication time-out", 2: "mechanical time-out (the mount is blocked "
          "or needs cleaning/frequency search)", 3: "command not supported", 4: "value out of "
          "range", 5: "module isolated", 6: "module out of isolation", 7: "initialising error",
          8: "thermal error (let it cool)", 9: "busy", 10: "sensor error", 11: "motor error",
          12: "out of range", 13: "over current"}
MODELS = {0x0E: "ELL14", 0x12: "ELL18", 0x0F: "ELL15", 0x08: "ELL8"}

ELLIPTEC_SCHEMA: dict[str, Setting] = {
    **port_settings(9600, 1.0),
    "address": Setting("str", "0", "module address on the bus (0-9, A-F)",
                       choices=tuple("0123456789ABCDEF")),
    "offset_deg": Setting("float", 0.0, "mount angle at which the analyzer is parallel to the "
                          "projector's polarizer", "deg", min=-360.0, max=360.0),
    "pulses_per_degree": Setting("float", 0.0, "encoder pulses per degree; 0 = as the module "
                                 "reports (ELL14: 143360 / 360 = 398.2)", "1/deg", min=0.0),
    "tolerance_deg": Setting("float", 0.05, "how close the reported angle must come", "deg",
                             min=0.0, max=5.0),
}


def _hex32(value: int) -> str:
    return f"{value & 0xFFFFFFFF:08X}"


def _signed32(text: str) -> int:
    v = int(text, 16)
    return v - (1 << 32) if v & 0x80000000 else v


class ElliptecAnalyzer(SerialDevice):
    """An Elliptec rotation mount holding the analyzer; Analyzer, Stoppable, Homing,
    AngleReadback, Identified."""

    model = "elliptec"

    def __init__(self, settings: dict[str, Any], context=None) -> None:
        super().__init__(settings, context)
        self.addr = settings["address"]
        self.scale = settings["pulses_per_degree"] or 143360 / 360.0
        self._reply = re.compile(rf"{self.addr}(IN|GS|PO|BO|BS|HO|GV|GJ)([0-9A-Fa-f]*)$")

    # ---- protocol -------------------------------------------------------------------------------

    def _read(self, what: str, timeout_s: float | None = None) -> tuple[str, str]:
        """The next reply from our address: (code, data); busy notices are skipped."""
        for _ in range(10):
            line = self.link.read_line(what, timeout_s)
            m = self._reply.search(line)
            if m is None:
                self._noise(line)
                continue
            if m.start() > 0:
                self._noise(line[:m.start()])
            if m.group(1) in ("BO", "BS"):
                continue
            return m.group(1), m.group(2)
        raise DeviceError(f"{self.link.name}: no reply from address {self.addr} to {what}; "
                          "is the address right (0 unless changed)?")

    def _ask(self, command: str, what: str, timeout_s: float | None = None) -> tuple[str, str]:
        self.link.write(f"{self.addr}{command}".encode("ascii"), what)
        code, data = self._read(what, timeout_s)
        if code == "GS" and data and int(data, 16) != 0:
            status = int(data, 16)
            raise DeviceError(f"{self.link.name}: the mount answered {what} with status "
                              f"{status} ({STATUS.get(status, 'reserved')}).")
        return code, data

    def _handshake(self) -> None:
        self.link.discard_input()
        code, data = self._ask("in", "the information request (in)")
        if code != "IN" or len(data) < 30:
            raise DeviceError(f"{self.link.name}: unexpected reply {code}{data} to 'in'; is it "
                              "an Elliptec module?")
        kind = int(data[0:2], 16)
        travel, pulses = int(data[18:22], 16), int(data[22:30], 16)
        if not self.settings["pulses_per_degree"] and travel and pulses:
            self.scale = pulses / travel
        self.ident = type(self.ident)(model=MODELS.get(kind, f"ELL{kind}"),
                                      serial_number=data[2:10], firmware=f"{int(data[14:16], 16)}",
                                      vendor="Thorlabs Elliptec")
        self.read_angle()

    # ---- role -----------------------------------------------------------------------------------

    def _mount_angle(self) -> float:
        code, data = self._ask("gp", "the position request (gp)")
        if code != "PO":
            raise DeviceError(f"{self.link.name}: expected a position, got {code}{data}.")
        return _signed32(data) / self.scale

    def read_angle(self) -> float:
        """The analyzer angle (degrees, relative to the polarizer)."""
        self._position = self._mount_angle() - self.settings["offset_deg"]
        return self._position

    def set_angle(self, degrees: float) -> None:
        angle = finite_degrees(degrees, self.link.name)
        self.stopping.clear()
        mount = (angle + self.settings["offset_deg"]) % 360.0
        self._move(f"ma{_hex32(round(mount * self.scale))}", f"the move to {angle:g}°")
        if self.stopping.is_set():
            raise self._stopped(self._position)
        err = (self._position - angle + 180.0) % 360.0 - 180.0
        if abs(err) > self.settings["tolerance_deg"]:
            raise DeviceError(f"{self.link.name}: the move to {angle:g}° ended at "
                              f"{self._position:.3f}° ({abs(err):.3f}° off); run a frequency "
                              "search (Elliptec software) or clean the mount.")

    def _move(self, command: str, what: str) -> None:
        left = self.context.time_left()
        wait = 10.0 if left == float("inf") else max(left - 0.5, 0.1)
        try:
            code, data = self._ask(command, what, wait)
        except DeviceTimeout:
            raise DeviceTimeout(f"{self.link.name}: no reply to {what} ({command!r}); the mount "
                                "did not report the end of the move. Check power and cable; "
                                "raise [analyzer.timeouts] set_angle if it is slow.") from None
        if code == "PO":
            self._position = _signed32(data) / self.scale - self.settings["offset_deg"]
        else:
            self.read_angle()

    def home(self) -> None:
        self.stopping.clear()
        self._move("ho0", "homing (ho0)")

    def stop(self) -> None:
        """``st`` (stop motion), sent without the link's lock."""
        self.stopping.set()
        if self.link.is_open:
            try:
                self.link.write_now(f"{self.addr}st".encode("ascii"), "stop (st)")
            except DeviceError:
                pass
