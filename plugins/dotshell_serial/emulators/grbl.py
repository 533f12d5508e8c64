"""A GRBL v1.1 controller with a rotation axis on X (degrees), as seen on its serial port.

Implements what :mod:`dotshell_serial.grbl` and a careful user use: the greeting after a soft
reset, ``$I``, ``$X``, ``$H``, ``G90``/``G0``/``G1 F`` moves on X, ``ok``/``error:N``, and the
realtime bytes ``?`` (status report), ``!`` (feed hold), ``~`` (cycle start), ``0x18`` (reset;
while moving it raises ALARM:3 like the real one). Faults: ``error`` → ``error:9`` to motion and
homing, ``alarm`` → ``ALARM:1`` (hard limit) mid-move, ``stuck``, ``silence``, ``garbage``,
``vanish``.
"""

from __future__ import annotations

import re
import time

from dotshell_serial.emulators.pty import LineEmulator

VERSION = "1.1h"
_MOVE = re.compile(r"^(?:G90\s*)?(?:G0|G1(?:\s*F[\d.]+)?)\s*X\s*(-?[\d.]+)$", re.I)


class GrblEmulator(LineEmulator):
    name = "grbl"

    def __init__(self, *args, homing_enabled: bool = True, home_time_s: float = 0.3,
                 alarm_at_start: bool = False, error_code: int = 9, **kwargs) -> None:
        self.homing_enabled = homing_enabled
        self.home_time_s = home_time_s
        self.alarm_at_start = alarm_at_start
        self.error_code = error_code
        self.state = "Idle"
        self._hold_until = 0.0
        self._home_done_at: float | None = None
        super().__init__(*args, **kwargs)

    # ---- realtime bytes -------------------------------------------------------------------------

    def feed(self, data: bytes) -> None:
        rest = bytearray()
        for b in data:
            if b == 0x3F:  # ?
                self._report()
            elif b == 0x21:  # !
                self.log_command("!")
                self._feed_hold()
            elif b == 0x7E:  # ~
                self.log_command("~")
                if self.state.startswith("Hold"):
                    self.state = "Idle"
                    if self._pending_target is not None:
                        self.state = "Run"
                        self.begin_move(self._pending_target)
                        self._pending_target = None
            elif b == 0x18:
                self.log_command("reset")
                self._reset()
            else:
                rest.append(b)
        if rest:
            super().feed(bytes(rest))

    def _report(self) -> None:
        self._tick_state()
        self.send(f"<{self.state}|MPos:{self.angle:.3f},0.000,0.000|FS:0,0>\r\n".encode())

    def _feed_hold(self) -> None:
        if self.state == "Run":
            self.halt()  # (decelerates within ~0.05 s in this model)
            self._pending_target = self._target_left
            self.state = "Hold:1"
            self._hold_until = time.monotonic() + 0.05
        elif self.state == "Idle":
            self.state = "Hold:0"

    def _reset(self) -> None:
        if self.state in ("Run", "Hold:1", "Home"):
            self.halt()
            self.send(b"ALARM:3\r\n")
            self.state = "Alarm"
        elif self.state.startswith("Hold"):
            self.state = "Idle"
        self._home_done_at = None
        self.on_plug(keep_state=True)
        self._greet()

    def _greet(self) -> None:
        self.send(f"\r\nGrbl {VERSION} ['$' for help]\r\n".encode())
        if self.state == "Alarm":
            self.send(b"[MSG:'$H'|'$X' to unlock]\r\n")

    def on_plug(self, keep_state: bool = False) -> None:
        super().on_plug()
        self._pending_target = None
        self._target_left = None
        if not keep_state:
            self.state = "Alarm" if self.alarm_at_start else "Idle"

    def _tick_state(self) -> None:
        now = time.monotonic()
        if self.state == "Hold:1" and now >= self._hold_until:
            self.state = "Hold:0"
        if self.state == "Home" and self._home_done_at is not None and now >= self._home_done_at:
            self.angle = 0.0
            self.state = "Idle"
            self._home_done_at = None
            self.reply("ok")

    def _advance(self, now: float) -> None:
        super()._advance(now)
        self._tick_state()

    def on_move_done(self) -> None:
        self.state = "Idle"
        self._target_left = None

    def on_limit(self) -> None:
        self.state = "Alarm"
        self.send(b"ALARM:1\r\n")

    # ---- lines ----------------------------------------------------------------------------------

    def line(self, text: str) -> None:
        cmd = text.upper().replace(" ", "")
        if cmd == "$I":
            self.reply(f"[VER:{VERSION}.20190825:EMU-0001]")
            self.reply("[OPT:V,15,128]")
            self.reply("ok")
        elif cmd == "$X":
            if self.state == "Alarm":
                self.state = "Idle"
                self.reply("[MSG:Caution: Unlocked]")
            self.reply("ok")
        elif cmd == "$H":
            self._home()
        elif cmd == "$$":
            for key, value in (("$22", int(self.homing_enabled)), ("$100", "80.000"),
                               ("$110", f"{self.speed_deg_s * 60:.3f}")):
                self.reply(f"{key}={value}")
            self.reply("ok")
        elif (m := _MOVE.match(text.strip())) is not None:
            self._move_to(float(m.group(1)))
        elif cmd in ("G90", "G91", "G21"):
            self.reply("ok")
        else:
            self.reply("error:20")

    def _home(self) -> None:
        if self.refuse():
            self.reply(f"error:{self.error_code}")
        elif not self.homing_enabled:
            self.reply("error:5")
        elif self.state not in ("Idle", "Alarm"):
            self.reply("error:8")
        else:
            self.state = "Home"
            self._home_done_at = time.monotonic() + self.home_time_s

    def _move_to(self, target: float) -> None:
        if self.refuse() or self.state == "Alarm":
            self.reply(f"error:{9 if self.state == 'Alarm' else self.error_code}")
            return
        self.reply("ok")
        self._target_left = target
        self.state = "Run"
        self.begin_move(target)
