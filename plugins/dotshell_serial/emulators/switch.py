"""A generic serial light-source switch (a laser driver or relay box with a text interface).

Answers the configured on/off commands with ``OK`` and ``STATE?`` with ``ON``/``OFF``. Faults:
``error`` → ``ERR 3 interlock open``, ``silence``, ``garbage``, ``vanish`` (``stuck`` and ``alarm``
do not apply to a switch).
"""

from __future__ import annotations

from dotshell_serial.emulators.pty import LineEmulator


class SwitchEmulator(LineEmulator):
    name = "switch"

    def __init__(self, *args, on_command: str = "ON", off_command: str = "OFF",
                 query_command: str = "STATE?", **kwargs) -> None:
        self.on_command, self.off_command, self.query_command = on_command, off_command, query_command
        self.on = False
        super().__init__(*args, **kwargs)

    def line(self, text: str) -> None:
        if text in (self.on_command, self.off_command) and self.refuse():
            self.reply("ERR 3 interlock open")
        elif text == self.on_command:
            self.on = True
            self.reply("OK")
        elif text == self.off_command:
            self.on = False
            self.reply("OK")
        elif text == self.query_command:
            self.reply("ON" if self.on else "OFF")
        else:
            self.reply("ERR 1 unknown command")
