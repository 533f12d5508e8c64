"""GRBL controllers driving a rotation axis (the Arduino turntables of open-source scanners).

Protocol: GRBL v1.1 (github.com/gnea/grbl, doc/markdown/interface.md, realtime_cmds.md,
doc/csv/error_codes_en_US.csv, alarm_codes_en_US.csv). Lines end in ``\\n``; every line is
answered ``ok`` or ``error:N``; ``ALARM:N`` and ``[MSG:...]`` may come at any time. Realtime
bytes act at once, outside the line buffer: ``?`` status report
(``<Idle|MPos:30.000,0.000,0.000|FS:0,0>``), ``!`` feed hold, ``~`` cycle start, ``0x18`` soft
reset (answered by the ``Grbl 1.1h ['$' for help]`` greeting).

The axis is set up in degrees (``$100`` = steps per degree for X). ``move_to`` sends
``G90 G0 X<deg>``, then polls ``?`` until ``Idle`` at the target. ``stop()`` sends a feed hold
(``!``) at once; the waiting move then resets GRBL once the hold is complete (``Hold:0``), which
discards the rest of the motion without losing position.
"""

from __future__ import annotations

import re
import time
from typing import Any

from dotshell.errors import DeviceError, DeviceTimeout
from dotshell.settings import Setting

from dotshell_serial.base import (MotionWatch, SerialDevice, finite_degrees, motion_settings,
                                  port_settings)

#: GRBL v1.1 error codes (doc/csv/error_codes_en_US.csv), in short.
ERRORS = {
    1: "G-code words need a letter and a value", 2: "bad or missing number",
    3: "unknown '$' command", 4: "negative value where a positive one is needed",
    5: "homing is not enabled ($22=0)", 6: "step pulse under 3 µs",
    7: "EEPROM read failed, defaults restored", 8: "'$' command needs GRBL to be idle",
    9: "G-code is locked out during an alarm or jog (home with $H or unlock with $X)",
    10: "soft limits need homing enabled", 11: "line too long",
    12: "setting exceeds the maximum step rate", 13: "safety door open",
    14: "build info or startup line too long", 15: "jog target exceeds machine travel",
    16: "invalid jog command", 17: "laser mode needs PWM output",
    20: "unsupported or invalid G-code", 21: "two commands of one modal group in a block",
    22: "feed rate not set", 23: "integer value required", 24: "two commands need axis words",
    25: "repeated G-code word", 26: "no axis words for a command that needs them",
    27: "invalid line number", 28: "missing value word", 29: "G59.x not supported",
    30: "G53 needs G0 or G1", 31: "unused axis words", 32: "arc needs an in-plane axis word",
    33: "invalid motion target", 34: "invalid arc radius", 35: "arc needs an offset word",
    36: "unused value words", 37: "tool length offset on the wrong axis",
    38: "tool number too high",
}

#: GRBL v1.1 alarm codes (doc/csv/alarm_codes_en_US.csv), with what to do.
ALARMS = {
    1: "hard limit triggered; position is likely lost — clear the limit switch and home ($H)",
    2: "soft limit: the target exceeds the machine travel ($130 for X); position kept — "
       "unlock ($X) and check the angle or the travel setting",
    3: "reset while moving; position is likely lost — home ($H)",
    4: "probe fail (probe not in its expected initial state)",
    5: "probe fail (no contact within travel)",
    6: "homing fail: the homing cycle was reset",
    7: "homing fail: safety door opened during homing",
    8: "homing fail: pull-off did not clear the limit switch — increase $27 or check wiring",
    9: "homing fail: no limit switch found within the search distance — check wiring and "
       "$130",
}

GRBL_SCHEMA: dict[str, Setting] = {
    **port_settings(115200, 2.0),
    **motion_settings(),
    "axis": Setting("str", "X", "GRBL axis that turns the stage (set up in degrees: $100 = "
                    "steps per degree)", choices=("X", "Y", "Z", "A", "B", "C")),
    "feed_deg_per_min": Setting("float", 0.0, "rotation speed for moves (G1 F...); 0 = rapid "
                                "moves at the axis' maximum rate ($110)", "deg/min", min=0.0),
    "tolerance_deg": Setting("float", 0.01, "how close the read-back angle must come to the "
                             "target", "deg", min=0.0, max=5.0),
    "poll_interval_s": Setting("float", 0.05, "time between status reports while moving "
                               "(GRBL recommends at most 5 per second on slow links)", "s",
                               min=0.005, max=1.0),
    "startup_s": Setting("float", 3.0, "how long to wait for the greeting after opening the "
                         "port (an Arduino resets when its port opens)", "s", min=0.1,
                         max=30.0),
}

#: a complete GRBL reply ending the line (noise may come before it)
_TOKEN = re.compile(r"(?:ok|error:\d+|ALARM:\d+|<[^<>]*>|\[[^\[\]]*\]|Grbl \S+.*)$")
_STATUS = re.compile(r"<([A-Za-z]+)(?::(\d))?\|(?:.*?)MPos:([-\d.]+(?:,[-\d.]+)*)")
_AXES = "XYZABC"


class GrblStage(SerialDevice):
    """A rotation stage on a GRBL controller; Stage, Stoppable, Homing, AngleReadback,
    Identified."""

    model = "grbl"

    def __init__(self, settings: dict[str, Any], context=None) -> None:
        super().__init__(settings, context)
        self._axis = _AXES.index(settings["axis"])
        self.alarm = ""

    # ---- protocol -------------------------------------------------------------------------------

    def _handshake(self) -> None:
        self.link.discard_input()
        self.link.write(b"\x18", "soft reset (Ctrl-X)")
        greeting = self._await_greeting(self.settings["startup_s"])
        version = greeting.split()[1] if len(greeting.split()) > 1 else ""
        info = self._command("$I", "build info ($I)")
        ver = next((line[5:-1] for line in info if line.startswith("[VER:")), version)
        build, _, name = ver.partition(":")
        self.ident = type(self.ident)(model="GRBL controller", firmware=build or version,
                                      serial_number=name, vendor="grbl")
        state, pos = self._status("the first status report (?)")
        self._position = pos
        if state == "Alarm":
            self.context.log.warn(f"{self.link.name} is in ALARM state after reset (homing "
                                  "required, or a limit switch is pressed): moves are locked "
                                  "until it is homed ([stage] home = \"on_connect\") or "
                                  "unlocked with $X")

    def _read(self, what: str, timeout_s: float | None = None) -> str:
        """The next reply line, from its first GRBL token on (noise before it is reported)."""
        line = self.link.read_line(what, timeout_s)
        m = _TOKEN.search(line)
        if m is None:
            self._noise(line)
            return ""
        if m.start() > 0:
            self._noise(line[:m.start()])
        return line[m.start():]

    def _await_greeting(self, timeout_s: float) -> str:
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            try:
                line = self._read("the reset (waiting for the 'Grbl ...' greeting)",
                                  max(left, 0.01))
            except DeviceTimeout:
                raise DeviceTimeout(
                    f"{self.link.name}: no 'Grbl' greeting within {timeout_s:g} s after a soft "
                    f"reset. Is it a GRBL controller, powered, at {self.link.baudrate} baud? "
                    "(another firmware or baud rate answers nothing or garbage)") from None
            if line.startswith("Grbl "):
                return line
            self._async_line(line)

    def _async_line(self, line: str) -> None:
        """Lines GRBL may send at any time."""
        if line.startswith("ALARM:"):
            code = int(line[6:]) if line[6:].isdigit() else 0
            self.alarm = line
            raise DeviceError(f"{self.link.name}: {line} — {ALARMS.get(code, 'unknown alarm')}.")
        if line.startswith("[MSG:"):
            self.context.log.info(f"GRBL says {line[5:-1]}")

    def _command(self, line: str, what: str, timeout_s: float | None = None) -> list[str]:
        """Send one line; the lines before its ``ok``. ``error:N`` → DeviceError."""
        self.link.write(line.encode("ascii") + b"\n", what)
        out = []
        while True:
            reply = self._read(what, timeout_s)
            if reply == "ok":
                return out
            if reply.startswith("error:"):
                code = int(reply[6:]) if reply[6:].isdigit() else 0
                raise DeviceError(f"{self.link.name}: GRBL refused {line!r} with {reply} "
                                  f"({ERRORS.get(code, 'unknown error')}).")
            if reply.startswith(("ALARM:", "[MSG:")):
                self._async_line(reply)
            elif reply:
                out.append(reply)

    def _status(self, what: str = "a status report (?)") -> tuple[str, float]:
        """(state, axis position in degrees) from a ``?`` report."""
        self.link.write_now(b"?", what)
        for _ in range(50):
            line = self._read(what)
            if line.startswith("<"):
                m = _STATUS.match(line)
                if m is None:
                    raise DeviceError(f"{self.link.name}: unreadable status report {line!r}; "
                                      "is it GRBL v1.1 with machine positions in reports "
                                      "($10=1)?")
                coords = m.group(3).split(",")
                self._state = m.group(1) + (f":{m.group(2)}" if m.group(2) else "")
                return self._state, float(coords[self._axis])
            if line:
                self._async_line(line)
        raise DeviceError(f"{self.link.name}: no status report among 50 replies to '?'; the "
                          "link is noisy — check the cable and baud rate.")

    # ---- role -----------------------------------------------------------------------------------

    def move_to(self, degrees: float) -> None:
        target = finite_degrees(degrees, self.link.name)
        state, _ = self._status()
        if state.startswith("Hold"):  # a stop() while idle leaves GRBL holding: clear it
            self._reset()
            state, _ = self._status()
        if state == "Alarm":
            self._unlock_and_home(f"the move to {target:g}°")
        self.stopping.clear()
        feed = self.settings["feed_deg_per_min"]
        motion = f"G1 F{feed:g}" if feed > 0 else "G0"
        self._command(f"G90 {motion} {self.settings['axis']}{target:.4f}",
                      f"the move to {target:g}°")
        self._wait_until_at(target, f"the move to {target:g}°")

    def _unlock_and_home(self, what: str) -> None:
        """GRBL in ALARM locks every move; after a limit or a reset the position is likely
        lost, so unlock (``$X``) and home (``$H``) before ``what``, saying so."""
        self.context.log.warn(f"GRBL is in ALARM ({self.alarm or 'after a reset'}) before "
                              f"{what}: unlocking ($X) and homing ($H), the position being "
                              "likely lost")
        self._command("$X", "the unlock ($X)")
        self.home()

    def _wait_until_at(self, target: float | None, what: str) -> None:
        tol = self.settings["tolerance_deg"]
        watch = MotionWatch(self, what)
        while True:
            if self.stopping.is_set():
                raise self._finish_stop()
            state, pos = self._status()
            self._position = pos
            if state == "Alarm":
                raise DeviceError(f"{self.link.name}: GRBL went into ALARM during {what} "
                                  f"({self.alarm or 'no alarm code seen'}) at {pos:.3f}°.")
            if state == "Idle" and (target is None or abs(pos - target) <= tol):
                return
            if state == "Idle" and target is not None:
                raise DeviceError(f"{self.link.name}: {what} ended at {pos:.3f}°, "
                                  f"{abs(pos - target):.3f}° from the target (tolerance "
                                  f"{tol:g}°); steps were lost or $100 is wrong.")
            watch.update(pos)
            if self.context.time_left() < 2 * self.settings["poll_interval_s"] + 0.5:
                self.link.write_now(b"!", "a feed hold")
                raise DeviceTimeout(f"{self.link.name}: {what} did not finish in time (at "
                                    f"{pos:.3f}°, state {state}); stopped it with a feed hold. "
                                    "The axis may be stalled or blocked; if it is just slow, "
                                    "raise [stage.timeouts] move_to.")
            time.sleep(self.settings["poll_interval_s"])

    def _finish_stop(self) -> DeviceError:
        """After the feed hold: wait for Hold:0, reset to drop the rest of the motion."""
        deadline = time.monotonic() + 5.0
        state, _ = self._status("a status report after the feed hold")
        while state not in ("Hold:0", "Idle", "Alarm") and time.monotonic() < deadline:
            time.sleep(0.02)
            state, _ = self._status("a status report after the feed hold")
        self._reset()
        _, self._position = self._status("a status report after the reset")
        return self._stopped(self._position)

    def _reset(self) -> None:
        self.link.write_now(b"\x18", "soft reset (Ctrl-X)")
        self._await_greeting(self.settings["startup_s"])

    def stop(self) -> None:
        """Feed hold now (``!``), without the link's lock; the waiting move finishes the stop."""
        self.stopping.set()
        if self.link.is_open:
            try:
                self.link.write_now(b"!", "a feed hold (!)")
            except DeviceError:
                pass

    def home(self) -> None:
        """``$H``: GRBL answers ``ok`` when the homing cycle is done."""
        self.stopping.clear()
        self._state = "Home"
        self._command("$H", "the homing cycle ($H)", max(self.context.time_left(), 1.0)
                      if self.context.time_left() != float("inf") else 120.0)
        self.alarm = ""
        _, self._position = self._status()

    def read_angle(self) -> float:
        _, self._position = self._status()
        return self._position
