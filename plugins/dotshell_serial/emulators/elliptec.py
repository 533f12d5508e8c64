"""A Thorlabs Elliptec ELL14 rotation mount (address 0) on its serial port.

Commands arrive without a terminator and are parsed by their known lengths: ``in``, ``gs``,
``gp``, ``ma`` + 8 hex, ``ho`` + direction, ``st``. A move is answered with ``PO`` + position when
it ends (or ``GS`` + a status code). Faults: ``error`` → ``GS02`` (mechanical time-out) to moves,
``alarm`` → the move stops halfway with ``GS02``, ``stuck``, ``silence``, ``garbage``, ``vanish``.
"""

from __future__ import annotations

from dotshell_serial.emulators.pty import PtyEmulator

#: data characters after the 3-character header, per command
_LENGTHS = {"in": 0, "gs": 0, "gp": 0, "ma": 8, "ho": 1, "st": 0}


class ElliptecEmulator(PtyEmulator):
    name = "elliptec"

    def __init__(self, *args, serial_number: str = "11400123", pulses: int = 143360,
                 **kwargs) -> None:
        self.serial_number = serial_number
        self.pulses = pulses
        self._buf = ""
        self._reply_when_done = False
        super().__init__(*args, speed_deg_s=kwargs.pop("speed_deg_s", 430.0), **kwargs)

    def on_plug(self) -> None:
        self._buf = ""

    def _pos(self) -> str:
        return f"{round(self.angle % 360.0 * self.pulses / 360.0) & 0xFFFFFFFF:08X}"

    def _say(self, text: str) -> None:
        self.send(f"0{text}\r\n".encode("ascii"))

    def feed(self, data: bytes) -> None:
        self._buf += data.decode("ascii", errors="replace")
        while len(self._buf) >= 3:
            addr, cmd = self._buf[0], self._buf[1:3]
            if cmd not in _LENGTHS:
                self._buf = self._buf[1:]  # not a command start: resynchronise
                continue
            n = _LENGTHS[cmd]
            if len(self._buf) < 3 + n:
                return
            arg, self._buf = self._buf[3:3 + n], self._buf[3 + n:]
            if addr != "0":
                continue
            self.log_command(cmd + arg)
            self._command(cmd, arg)

    def _command(self, cmd: str, arg: str) -> None:
        if cmd == "in":
            self._say(f"IN0E{self.serial_number}2023{0x17:02X}{0x81:02X}{360:04X}"
                      f"{self.pulses:08X}")
        elif cmd == "gs":
            self._say("GS00")
        elif cmd == "gp":
            self._say(f"PO{self._pos()}")
        elif cmd == "st":
            if self.moving:
                self.halt()
                self._reply_when_done = False
                self._say(f"PO{self._pos()}")
        elif cmd in ("ma", "ho"):
            if self.refuse():
                self._say("GS02")
                return
            target = 0.0 if cmd == "ho" else int(arg, 16) * 360.0 / self.pulses
            if target > 180.0 + self.angle % 360.0:  # the shorter way round
                target -= 360.0
            self.angle %= 360.0
            self._reply_when_done = True
            self.begin_move(target)

    def on_move_done(self) -> None:
        if self._reply_when_done:
            self._reply_when_done = False
            self.angle %= 360.0
            self._say(f"PO{self._pos()}")

    def on_limit(self) -> None:
        self._reply_when_done = False
        self._say("GS02")
