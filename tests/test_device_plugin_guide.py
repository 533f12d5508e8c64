"""docs/writing-a-device-plugin.md stays true: its complete serial stage driver, taken from the
page, passes the conformance kit against the Zaber emulator and shows its settings' units,
limits and choices in `dotshell plugins --settings`."""

import re
import types

from conftest import ROOT
from dotshell.testing import assert_device_conforms

GUIDE = ROOT / "docs" / "writing-a-device-plugin.md"


def guide_module():
    text = GUIDE.read_text()
    code = next(block for block in re.findall(r"```python\n(.*?)```", text, re.S)
                if "class MyStage" in block)
    module = types.ModuleType("dotshell_mystage")
    exec(compile(code, str(GUIDE), "exec"), module.__dict__)
    return module


def test_the_guide_driver_conforms_on_the_emulator(dotshell_pm, serial_emulator):
    dotshell_pm.register(guide_module(), name="mystage")
    emu = serial_emulator("zaber")
    assert_device_conforms(dotshell_pm, "stage", "mystage", {"port": emu.port},
                           failing_settings={"port": "/dev/does-not-exist"})


def test_plugins_settings_show_units_limits_and_choices(capsys, monkeypatch, dotshell_pm):
    from rich.console import Console

    import dotshell.cli
    import dotshell.plugins
    from dotshell.cli import main

    dotshell_pm.register(guide_module(), name="mystage")
    monkeypatch.setattr(dotshell.plugins, "_default", dotshell_pm)
    monkeypatch.setattr(dotshell.cli, "out", Console(width=400, highlight=False))
    assert main(["plugins", "--settings"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    for row in ("int [baud]", "(choices: 9600, 115200)", "float [1/deg] ≥ 1",
                "float [s] 0.005..1"):
        assert row in out, row
    # the first-party serial backends too
    assert "(choices: X, Y, Z, A, B, C)" in out and "float [deg] 0..5" in out
