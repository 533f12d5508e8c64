"""Zaber rotary stages over the Zaber ASCII protocol (X-RSW, X-RST, RSB series; X-MCB controllers).

Protocol: Zaber ASCII Protocol Manual (zaber.com/protocol-manual, "ASCII"). Commands
``/<device> <axis> [<id>] <command> [data]\\n``; replies
``@<device> <axis> [<id>] <OK|RJ> <IDLE|BUSY> <flag> <data>\\r\\n`` where the flag is ``--`` or the
most important warning (``F*`` faults, ``W*`` warnings, ``N*`` notices). Positions are
microsteps; ``microsteps_per_degree`` converts (4266.67 for an X-RSW60A: 0.000234375° per
microstep). Polls carry a message id so that the reply to a ``stop`` (sent without one, from
another thread) is never mistaken for a position.
"""

from __future__ import annotations

import itertools
import re
import time
from typing import Any

from dotshell.errors import DeviceError, DeviceTimeout
from dotshell.settings import Setting

from dotshell_serial.base import (MotionWatch, SerialDevice, finite_degrees, motion_settings,
                                  port_settings)

#: Warning flags (Zaber ASCII protocol manual, "Warning Flags"), in short.
FLAGS = {
    "FF": "critical system error — power-cycle the controller", "FN": "peripheral not supported",
    "FZ": "peripheral inactive (no stage detected)", "FH": "hardware emergency stop",
    "FV": "supply voltage out of range", "FO": "driver disabled at start-up",
    "FC": "current inrush error", "FM": "motor temperature error", "FD": "driver disabled",
    "FQ": "encoder error", "FS": "stalled and stopped — something blocks the stage",
    "FB": "stream bounds error", "FP": "interpolated path deviation",
    "FE": "limit error", "FT": "excessive twist", "WL": "unexpected limit trigger",
    "WV": "voltage out of range", "WT": "controller temperature high",
    "WS": "stalled, recovered", "WM": "displaced while stationary",
    "WP": "invalid calibration type", "WR": "no reference position — home the stage",
    "WH": "not homed — home the stage", "NC": "moved by manual control",
    "NI": "movement interrupted by a new command", "ND": "stream discontinuity",
    "NR": "value rounded", "NT": "value truncated", "NU": "setting update pending",
    "NJ": "joystick calibrating",
}
#: Rejection reasons (``RJ`` replies).
REJECTIONS = {
    "BADDATA": "the value is out of range or malformed",
    "BADCOMMAND": "the command is not known to this firmware",
    "BADAXIS": "there is no such axis", "DEVICEONLY": "the command must go to the device",
    "AGAIN": "the device is busy, try again", "FULL": "the command buffer is full",
    "PARKED": "the axis is parked (unpark it)", "DRIVERDISABLED": "the driver is disabled",
    "LOCKSTEP": "the axis is in a lockstep group", "STATUSBUSY": "the axis is busy",
    "NOACCESS": "the setting needs a higher access level",
}

ZABER_SCHEMA: dict[str, Setting] = {
    **port_settings(115200, 1.0),
    **motion_settings(),
    "device": Setting("int", 1, "device address in the daisy chain", min=1, max=99),
    "axis": Setting("int", 1, "axis number of the rotary stage", min=1, max=9),
    "microsteps_per_degree": Setting("float", 4266.666667, "microsteps per degree of the "
                                     "stage (X-RSW60A: 0.000234375° per microstep = 4266.67)",
                                     "1/deg", min=1.0),
    "tolerance_deg": Setting("float", 0.01, "how close the read-back angle must come to the "
                             "target", "deg", min=0.0, max=5.0),
    "poll_interval_s": Setting("float", 0.05, "time between position polls while moving", "s",
                               min=0.005, max=1.0),
}

_REPLY = re.compile(r"@(\d+) (\d+) (?:(\d+) )?(OK|RJ) (IDLE|BUSY) (\S\S) ?(.*)$")


class ZaberStage(SerialDevice):
    """A Zaber rotary stage; Stage, Stoppable, Homing, AngleReadback, Identified."""

    model = "zaber"

    def __init__(self, settings: dict[str, Any], context=None) -> None:
        super().__init__(settings, context)
        self._ids = itertools.cycle(range(10, 100))
        self.flag = "--"
        self._warned = "--"

    # ---- protocol -------------------------------------------------------------------------------

    def _query(self, command: str, what: str, axis: int | None = None,
               timeout_s: float | None = None) -> tuple[str, str, str]:
        """Send with a fresh message id; (OK|RJ, IDLE|BUSY, data) of the reply to it."""
        msg_id = next(self._ids)
        ax = self.settings["axis"] if axis is None else axis
        with self.link.lock:
            self.link.write(f"/{self.settings['device']} {ax} {msg_id} {command}\n".encode(),
                            what)
            for _ in range(20):  # replies to other messages (a stop's) are skipped
                line = self.link.read_line(what, timeout_s).strip()
                m = _REPLY.search(line)  # the reply ends the line; noise may come before it
                if m is None:
                    if line.startswith(("!", "#")):  # alerts and info lines
                        continue
                    raise DeviceError(f"{self.link.name}: unreadable reply {line!r} to {what}; "
                                      "check the baud rate (115200) and that the controller "
                                      "speaks the ASCII protocol (not Binary).")
                if m.start() > 0:
                    self._noise(line[:m.start()])
                if m.group(3) is None or int(m.group(3)) != msg_id:
                    continue
                self.flag = m.group(6)
                return m.group(4), m.group(5), m.group(7).strip()
        raise DeviceError(f"{self.link.name}: no reply with message id {msg_id} to {what}.")

    def _ok(self, command: str, what: str, axis: int | None = None) -> tuple[str, str]:
        flag, state, data = self._query(command, what, axis)
        if flag == "RJ":
            raise DeviceError(f"{self.link.name}: the stage rejected {command!r} ({data}: "
                              f"{REJECTIONS.get(data, 'see the Zaber protocol manual')}).")
        self._check_flag(what)
        return state, data

    def _check_flag(self, what: str) -> None:
        if self.flag.startswith("F"):
            raise DeviceError(f"{self.link.name}: fault {self.flag} during {what} "
                              f"({FLAGS.get(self.flag, 'see the Zaber protocol manual')}); fix "
                              "the cause; dotshell clears the flag (warnings clear) before the "
                              "next move.")
        if self.flag[0] == "W" and self.flag != self._warned:
            self.context.log.warn(f"warning {self.flag}: {FLAGS.get(self.flag, '?')}")
        self._warned = self.flag

    def _handshake(self) -> None:
        self.link.discard_input()
        serial_no = self._ok("get system.serial", "the serial number query", axis=0)[1]
        device_id = self._ok("get deviceid", "the device id query", axis=0)[1]
        version = self._ok("get version", "the firmware version query", axis=0)[1]
        self.ident = type(self.ident)(model=f"Zaber device id {device_id}",
                                      serial_number=serial_no, firmware=version, vendor="Zaber")
        self.read_angle()

    # ---- role -----------------------------------------------------------------------------------

    def read_angle(self) -> float:
        state, data = self._ok("get pos", "the position query")
        try:
            self._position = int(data.split()[0]) / self.settings["microsteps_per_degree"]
        except (ValueError, IndexError):
            raise DeviceError(f"{self.link.name}: position reply {data!r} is not a number of "
                              "microsteps.") from None
        self._state = state.lower()
        return self._position

    def _clear_faults(self, what: str) -> None:
        """A fault flag left by an earlier move (a stall: ``FS``) blocks every move until it is
        cleared: ``warnings clear``, logged, before ``what``."""
        if self.flag.startswith("F"):
            self.context.log.warn(f"clearing fault {self.flag} "
                                  f"({FLAGS.get(self.flag, 'see the Zaber manual')}) before "
                                  f"{what} (warnings clear)")
            self._query("warnings clear", "clearing the warnings", axis=0)
            self.flag = self._warned = "--"

    def move_to(self, degrees: float) -> None:
        target = finite_degrees(degrees, self.link.name)
        self.stopping.clear()
        self._clear_faults(f"the move to {target:g}°")
        steps = round(target * self.settings["microsteps_per_degree"])
        self._ok(f"move abs {steps}", f"the move to {target:g}°")
        self._wait_idle(f"the move to {target:g}°", target)

    def _wait_idle(self, what: str, target: float | None) -> None:
        watch = MotionWatch(self, what, log_progress=target is None)
        while True:
            time.sleep(self.settings["poll_interval_s"])
            if self.stopping.is_set():
                self.read_angle()
                raise self._stopped(self._position)
            self.read_angle()
            if self._state == "idle":
                break
            watch.update(self._position)
            if self.context.time_left() < 2 * self.settings["poll_interval_s"] + 0.5:
                self.stop()
                raise DeviceTimeout(f"{self.link.name}: {what} did not finish in time (at "
                                    f"{self._position:.3f}°); stopped it. Check the stage; if "
                                    "it is just slow, raise [stage.timeouts] move_to.")
        tol = self.settings["tolerance_deg"]
        if target is not None and abs(self._position - target) > tol:
            raise DeviceError(f"{self.link.name}: {what} ended at {self._position:.3f}°, "
                              f"{abs(self._position - target):.3f}° off (flag {self.flag}: "
                              f"{FLAGS.get(self.flag, 'none')}).")

    def stop(self) -> None:
        """``stop`` (decelerates), sent without the link's lock."""
        self.stopping.set()
        if self.link.is_open:
            try:
                self.link.write_now(f"/{self.settings['device']} {self.settings['axis']} "
                                    "stop\n".encode(), "stop")
            except DeviceError:
                pass

    def home(self) -> None:
        self.stopping.clear()
        self._clear_faults("homing")
        left = self.context.time_left()
        self.context.log.info("homing" + ("" if left == float("inf") else
                                          f" (deadline {left:.0f} s: [stage.timeouts] home)"))
        self._ok("home", "homing")
        self._wait_idle("homing", None)
