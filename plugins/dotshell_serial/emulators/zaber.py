"""A Zaber ASCII rotary stage (device 1, axis 1) on its serial port.

Understands ``get pos``, ``get system.serial``, ``get deviceid``, ``get version``,
``move abs N``, ``stop``, ``home``, ``warnings [clear]`` and the empty (status) command, with or
without message ids. Faults: ``error`` → ``RJ ... BADDATA`` to moves and homing, ``alarm`` →
the stage stalls mid-move (flag ``FS``), ``stuck``, ``silence``, ``garbage``, ``vanish``.
"""

from __future__ import annotations

from dotshell_serial.emulators.pty import LineEmulator


class ZaberEmulator(LineEmulator):
    name = "zaber"

    def __init__(self, *args, microsteps_per_degree: float = 4266.666667,
                 serial_number: int = 33938, device_id: int = 50081, version: str = "7.25",
                 **kwargs) -> None:
        self.scale = microsteps_per_degree
        self.serial_number = serial_number
        self.device_id = device_id
        self.version = version
        self.warnings: set[str] = {"WR"}
        super().__init__(*args, **kwargs)

    def _flag(self) -> str:
        order = sorted(self.warnings, key=lambda f: "FWN".index(f[0]))
        return order[0] if order else "--"

    def _answer(self, axis: str, msg_id: str | None, ok: bool, data: str) -> None:
        busy = "BUSY" if self.moving else "IDLE"
        ident = f" {msg_id}" if msg_id is not None else ""
        self.reply(f"@01 {axis}{ident} {'OK' if ok else 'RJ'} {busy} {self._flag()} {data}")

    def line(self, text: str) -> None:
        if not text.startswith("/"):
            return
        parts = text[1:].split()
        if not parts or parts[0].lstrip("0") not in ("1", ""):
            return  # another device on the chain
        axis = parts[1] if len(parts) > 1 and parts[1].isdigit() else "0"
        rest = parts[2:] if len(parts) > 1 and parts[1].isdigit() else parts[1:]
        msg_id = rest[0] if rest and rest[0].isdigit() else None
        words = rest[1:] if msg_id is not None else rest
        self._command(axis, msg_id, words)

    def _command(self, axis: str, msg_id: str | None, words: list[str]) -> None:
        cmd = " ".join(words)
        getters = {"get pos": lambda: str(round(self.angle * self.scale)),
                   "get system.serial": lambda: str(self.serial_number),
                   "get deviceid": lambda: str(self.device_id),
                   "get version": lambda: self.version}
        if cmd in getters:
            self._answer(axis, msg_id, True, getters[cmd]())
        elif cmd == "":
            self._answer(axis, msg_id, True, "0")
        elif cmd == "stop":
            if self.moving:
                self.halt()
                self.warnings.add("NI")
            self._answer(axis, msg_id, True, "0")
        elif cmd == "warnings clear":
            flags = " ".join(sorted(self.warnings))
            self.warnings.clear()
            self._answer(axis, msg_id, True, f"{len(flags.split()):02d} {flags}".strip())
        elif cmd == "warnings":
            self._answer(axis, msg_id, True,
                         f"{len(self.warnings):02d} {' '.join(sorted(self.warnings))}".strip())
        elif words[:2] == ["move", "abs"] and len(words) == 3:
            self._move_abs(axis, msg_id, words[2])
        elif cmd == "home":
            if self.refuse():
                self._answer(axis, msg_id, False, "BADDATA")
                return
            self.warnings.discard("WR")
            self.warnings.discard("FS")
            self._answer(axis, msg_id, True, "0")
            self.begin_move(0.0)
        else:
            self._answer(axis, msg_id, False, "BADCOMMAND")

    def _move_abs(self, axis: str, msg_id: str | None, value: str) -> None:
        try:
            steps = int(value)
        except ValueError:
            self._answer(axis, msg_id, False, "BADDATA")
            return
        if self.refuse() or "FS" in self.warnings:
            self._answer(axis, msg_id, False, "BADDATA")
            return
        self.warnings.discard("NI")
        self.begin_move(steps / self.scale)
        self._answer(axis, msg_id, True, "0")

    def on_limit(self) -> None:
        self.warnings.add("FS")
