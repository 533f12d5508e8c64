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

    import dotshell.cli.app
    import dotshell.plugins
    from dotshell.cli.app import main

    dotshell_pm.register(guide_module(), name="mystage")
    monkeypatch.setattr(dotshell.plugins, "_default", dotshell_pm)
    monkeypatch.setattr(dotshell.cli.app, "out", Console(width=400, highlight=False))
    assert main(["plugins", "--settings"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    for row in ("int [baud]", "(choices: 9600, 115200)", "float [1/deg] ≥ 1",
                "float [s] 0.005..1"):
        assert row in out, row
    # the first-party serial backends too
    assert "(choices: X, Y, Z, A, B, C)" in out and "float [deg] 0..5" in out


def rt1_module():
    """The section-5 blocks (emulator, driver, tests) of the guide, in one module."""
    text = GUIDE.read_text()
    blocks = re.findall(r"```python\n(# (rt1_emulator|rt1_driver|test_rt1)\.py\n.*?)```", text,
                        re.S)
    assert [name for _, name in blocks] == ["rt1_emulator", "rt1_driver", "test_rt1"]
    module = types.ModuleType("dotshell_rt1")
    for code, _ in blocks:
        exec(compile(code, str(GUIDE), "exec"), module.__dict__)
    return module


def test_the_guide_protocol_exchanges_pass_and_a_wrong_request_is_named():
    import pytest

    from dotshell.backends import RigContext
    from dotshell.settings import validate_settings
    from dotshell_serial.protocol import scripted

    rt1 = rt1_module()
    rt1.test_rt1_speaks_its_protocol()
    table = rt1.RT1Stage(validate_settings(rt1.RT1_SETTINGS, {"port": "x"}, "rt1"), RigContext())
    with pytest.raises(AssertionError, match=r"exchange 1 of 1: the driver sent b'ID\?\\n' "
                                             r"where the script expects b'VER\?\\n'"):
        with scripted(table, [(b"VER?\n", b"")]):
            table.connect()


def test_the_guide_rt1_driver_passes_kit_v2_on_its_emulator(tmp_path, dotshell_pm):
    rt1 = rt1_module()
    dotshell_pm.register(rt1, name="rt1")
    rt1.test_rt1_conforms_on_its_emulator(tmp_path, dotshell_pm)


def test_the_guide_emulator_defines_its_own_fault(tmp_path, dotshell_pm):
    import pytest

    from dotshell.errors import DeviceError

    rt1 = rt1_module()
    dotshell_pm.register(rt1, name="rt1")
    with rt1.RT1Emulator(link=tmp_path / "rt1") as emu:
        assert rt1.RT1Emulator.fault_names()[-1] == "overheat"
        emu.set_fault("overheat")
        table = dotshell_pm.create("stage", "rt1", {"port": emu.port})
        table.connect()
        with pytest.raises(DeviceError, match=r"refused 'MOVE 10.000' \(over temperature\)"):
            table.move_to(10.0)
        table.close()
        with pytest.raises(ValueError, match="no fault 'melt'; its faults: error, silence, "
                                             "garbage, stuck, alarm, overheat"):
            emu.set_fault("melt")
    assert not emu.errors  # the model raised nothing


def test_emulate_refuses_an_unknown_fault_naming_the_emulators_faults(capsys):
    from dotshell.cli.app import main

    assert main(["emulate", "zaber", "--fault", "melt", "--seconds", "0.1"]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "no fault 'melt'; its faults: error, silence, garbage, stuck, alarm" in err
