"""A Thorlabs K10CR1 rotation mount (APT protocol) on its serial port.

Parses the host's 6-byte headers (and data of long messages) by hand from the APT
Communications Protocol and answers HW_REQ_INFO, MOT_REQ_STATUSUPDATE, MOT_MOVE_ABSOLUTE,
MOT_MOVE_HOME and MOT_MOVE_STOP like the controller does (source 0x50, destination 0x01). Faults:
``error`` → HW_RICHRESPONSE to moves and homing, ``alarm`` → the forward limit trips mid-move
(MOT_MOVE_STOPPED with the limit bit), ``stuck``, ``silence``, ``garbage``, ``vanish``.
"""

from __future__ import annotations

import struct
import time

from dotshell_serial.emulators.pty import PtyEmulator

SRC, HOST = 0x50, 0x01
MOVING_CW, MOVING_CCW, HOMING, HOMED, ENABLED = 0x10, 0x20, 0x200, 0x400, 0x80000000
FWD_LIMIT = 0x01
_NAMES = {0x0005: "HW_REQ_INFO", 0x0018: "HW_NO_FLASH_PROGRAMMING", 0x0210: "MOD_SET_CHANENABLE",
          0x0443: "MOT_MOVE_HOME", 0x0453: "MOT_MOVE_ABSOLUTE", 0x0465: "MOT_MOVE_STOP",
          0x0480: "MOT_REQ_STATUSUPDATE", 0x0011: "HW_START_UPDATEMSGS",
          0x0012: "HW_STOP_UPDATEMSGS"}


def short(msg_id: int, p1: int = 0, p2: int = 0) -> bytes:
    return struct.pack("<HBBBB", msg_id, p1, p2, HOST, SRC)


def long(msg_id: int, data: bytes) -> bytes:
    return struct.pack("<HHBB", msg_id, len(data), HOST | 0x80, SRC) + data


class AptEmulator(PtyEmulator):
    name = "apt"

    def __init__(self, *args, counts_per_degree: float = 136533.333333,
                 serial_number: int = 55000123, model: str = "K10CR1",
                 firmware: tuple[int, int, int] = (3, 0, 10), home_time_s: float = 0.3,
                 homed: bool = False, **kwargs) -> None:
        self.scale = counts_per_degree
        self.serial_number = serial_number
        self.model = model
        self.firmware = firmware
        self.home_time_s = home_time_s
        self.homed = homed
        self.limit = 0
        self._homing_until: float | None = None
        self._buf = b""
        super().__init__(*args, **kwargs)

    def on_plug(self) -> None:
        self._buf = b""

    # ---- framing --------------------------------------------------------------------------------

    def feed(self, data: bytes) -> None:
        self._buf += data
        while len(self._buf) >= 6:
            msg_id, length, dest, _source = struct.unpack_from("<HHBB", self._buf)
            if msg_id not in _NAMES:  # not a message start: resynchronise byte by byte
                self._buf = self._buf[1:]
                continue
            size = 6 + (length if dest & 0x80 else 0)
            if len(self._buf) < size:
                return
            frame, self._buf = self._buf[:size], self._buf[size:]
            self.log_command(_NAMES[msg_id])
            self._handle(msg_id, frame)

    def _status(self) -> bytes:
        bits = ENABLED | self.limit | (HOMED if self.homed else 0)
        if self._homing_until is not None:
            bits |= HOMING
        elif self.moving and self._move is not None:
            bits |= MOVING_CW if self._move[1] >= self._move[0] else MOVING_CCW
        counts = round(self.angle * self.scale)
        return struct.pack("<HllL", 1, counts, counts, bits)

    def _handle(self, msg_id: int, frame: bytes) -> None:
        if msg_id == 0x0005:
            major, interim, minor = self.firmware
            data = struct.pack("<l8sH4B48s12sHHH", self.serial_number, self.model.encode(), 16,
                               minor, interim, major, 0, b"APT Stepper Motor Controller", b"",
                               1, 0, 1)
            self.send(long(0x0006, data))
        elif msg_id == 0x0480:
            self.send(long(0x0481, self._status()))
        elif msg_id == 0x0453:
            _, counts = struct.unpack_from("<Hl", frame, 6)
            if self.refuse():
                self._error(0x0453, 10, "move rejected: motor not enabled")
            else:
                self.limit = 0
                self.begin_move(counts / self.scale)
        elif msg_id == 0x0443:
            if self.refuse():
                self._error(0x0443, 10, "homing rejected")
            else:
                self._homing_until = time.monotonic() + self.home_time_s
        elif msg_id == 0x0465 and (self.moving or self._homing_until is not None):
            self.halt()
            self._homing_until = None
            self.send(long(0x0466, self._status()))

    def _error(self, about: int, code: int, text: str) -> None:
        self.send(long(0x0081, struct.pack("<HH64s", about, code, text.encode())))

    def _advance(self, now: float) -> None:
        super()._advance(now)
        if self._homing_until is not None and now >= self._homing_until:
            self._homing_until = None
            self.angle, self.homed = 0.0, True
            self.send(short(0x0444, 1))

    def on_move_done(self) -> None:
        self.send(long(0x0464, self._status()))

    def on_limit(self) -> None:
        self.limit = FWD_LIMIT
        self.send(long(0x0466, self._status()))
