"""A generic serial light-source switch: any laser driver, LED controller or relay box that turns
on and off with text commands (``ON`` / ``OFF``, ``L1`` / ``L0``, ``OUTP ON`` ...).

The commands, the line terminator, the reply that means success and the prefix that means an
error are settings; a query command, if the device has one, is read back after switching so a
refused command (interlock open, key switch off) is caught.
"""

from __future__ import annotations

import time
from typing import Any

from dotshell.errors import DeviceError
from dotshell.settings import Setting

from dotshell_serial.base import SerialDevice, port_settings

TERMINATORS = {"CR": "\r", "LF": "\n", "CRLF": "\r\n"}

SWITCH_SCHEMA: dict[str, Setting] = {
    **port_settings(9600, 1.0),
    "on_command": Setting("str", "ON", "text that switches the source on"),
    "off_command": Setting("str", "OFF", "text that switches the source off"),
    "terminator": Setting("str", "CRLF", "what ends each command line",
                          choices=tuple(TERMINATORS)),
    "ok_reply": Setting("str", "OK", "reply that confirms a command; empty = the device "
                        "answers nothing"),
    "error_prefix": Setting("str", "ERR", "start of a reply that reports an error"),
    "query_command": Setting("str", "", "command whose reply is on_reply / off_reply (e.g. "
                             "STATE?); empty = no read-back"),
    "on_reply": Setting("str", "ON", "query reply meaning on"),
    "off_reply": Setting("str", "OFF", "query reply meaning off"),
    "settle_s": Setting("float", 0.0, "wait after switching (laser warm-up)", "s", min=0.0,
                        max=60.0),
}


class SerialSwitch(SerialDevice):
    """A light source switched over a serial port; LightSource, Identified."""

    model = "serial-switch"

    def __init__(self, settings: dict[str, Any], context=None) -> None:
        super().__init__(settings, context)
        self.on: bool | None = None

    def _line(self, text: str, what: str) -> None:
        self.link.write((text + TERMINATORS[self.settings["terminator"]]).encode("ascii"), what)

    def _reply(self, what: str, expected: tuple[str, ...]) -> str:
        """The first expected token (or an error reply) in the next line; noise reported."""
        line = self.link.read_line(what)
        err = self.settings["error_prefix"]
        for token in (err, *expected) if err else expected:
            i = line.rfind(token)  # the reply ends the line; noise may come before it
            if i >= 0:
                if i > 0:
                    self._noise(line[:i])
                if err and token == err:
                    raise DeviceError(f"{self.link.name}: the device answered {what} with "
                                      f"{line[i:]!r}; check its interlock, key switch and "
                                      "remote-control mode.")
                return token
        raise DeviceError(f"{self.link.name}: unexpected reply {line!r} to {what} (expected "
                          f"{' or '.join(map(repr, expected))}); check the command strings in "
                          "the profile against the device's manual.")

    def _handshake(self) -> None:
        self.link.discard_input()
        self.ident = type(self.ident)(model="serial light-source switch")
        if self.settings["query_command"]:
            self.on = self._query() == "on"

    def _query(self) -> str:
        s = self.settings
        self._line(s["query_command"], f"the state query {s['query_command']!r}")
        token = self._reply(f"the state query {s['query_command']!r}",
                            (s["on_reply"], s["off_reply"]))
        return "on" if token == s["on_reply"] else "off"

    def set(self, on: bool) -> None:
        s = self.settings
        command = s["on_command"] if on else s["off_command"]
        what = f"{command!r} (switch {'on' if on else 'off'})"
        self._line(command, what)
        if s["ok_reply"]:
            self._reply(what, (s["ok_reply"],))
        if s["query_command"] and self._query() != ("on" if on else "off"):
            raise DeviceError(f"{self.link.name}: after {what} the device reports it is "
                              f"{'off' if on else 'on'}; check its interlock and key switch.")
        self.on = bool(on)
        if s["settle_s"] > 0:
            time.sleep(s["settle_s"])

    def close(self) -> None:
        if self.link.is_open and self.on:
            try:  # leave a laser off
                self._line(self.settings["off_command"], "switch off on close")
            except DeviceError:
                pass
        super().close()

    def status(self) -> dict[str, Any]:
        out = super().status()
        out.pop("angle_deg", None)
        return {**out, "on": self.on}
