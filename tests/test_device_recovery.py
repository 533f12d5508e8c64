"""Device recovery that knows the device (issue 28): a stuck stage is named within seconds (not
after the 300 s home limit), homing logs its progress and deadline, a Zaber stall flag is cleared
(`warnings clear`) so the move can be retried, a GRBL alarm is unlocked ($X) and the stage
re-homed ($H) before the next move, and the garbage fault never sends XON/XOFF."""

from __future__ import annotations

import os

import pytest

from dotshell.backends import RigContext
from dotshell.errors import DeviceError
from dotshell.events import EventBus
from dotshell.rig.handles import DeviceHandle, DevicePolicy
from dotshell.pipeline.acquire import with_retries
from rig_server import user_dirs  # noqa: F401 (a fixture)
from stop_cases import wait_for


def handle(pm, emu, backend, lines, **settings):
    ctx = RigContext().for_device("stage", backend)
    ctx.log.listen(lambda level, text, when: lines.append(text))
    info = pm.backend("stage", backend)
    dev = pm.create("stage", backend, {"port": emu.port, **settings}, ctx)
    h = DeviceHandle("stage", backend, info.plugin, info.distribution, dev, ctx, DevicePolicy())
    h.connect()
    return h


@pytest.mark.parametrize("name,backend", [("zaber", "zaber"), ("grbl", "grbl"),
                                          ("apt", "thorlabs-apt")])
def test_a_stuck_stage_is_named_within_its_stall_time(dotshell_pm, serial_emulator, name,
                                                      backend):
    emu = serial_emulator(name)
    lines: list[str] = []
    h = handle(dotshell_pm, emu, backend, lines, stall_s=0.5)
    emu.faults.stuck = True
    try:
        with pytest.raises(DeviceError, match=r"is stuck — the device says it is moving but has "
                                              r"stayed at 0.00\d° for 0.\d s; stopped it"):
            h.move_to(45.0)  # the move_to timeout is 120 s: only the stall names it this early
    finally:
        h.shutdown()
    assert wait_for(lambda: not emu.moving, 5.0)  # stopped


def test_homing_logs_its_deadline_and_progress(dotshell_pm, serial_emulator):
    emu = serial_emulator("zaber", speed_deg_s=20.0)
    emu.angle = 30.0
    lines: list[str] = []
    h = handle(dotshell_pm, emu, "zaber", lines, progress_s=0.5)
    try:
        h.home()
    finally:
        h.shutdown()
    assert any("homing (deadline 300 s: [stage.timeouts] home)" in t for t in lines), lines
    progress = [t for t in lines if "homing: at " in t]
    assert progress and "s left of its deadline" in progress[0]
    assert emu.angle == 0.0


def test_a_zaber_stall_is_cleared_and_the_move_retried(dotshell_pm, serial_emulator):
    emu = serial_emulator("zaber", speed_deg_s=720.0)
    lines: list[str] = []
    h = handle(dotshell_pm, emu, "zaber", lines)
    emu.faults.alarm = True  # stalls half-way: flag FS, every move refused until cleared
    try:
        with_retries(lambda: h.move_to(90.0), 2, "move", EventBus())
    finally:
        h.shutdown()
    assert abs(emu.angle - 90.0) < 0.01
    assert any("clearing fault FS" in t and "warnings clear" in t for t in lines)
    assert any(c.endswith("warnings clear") for _, c in emu.commands)


def test_a_grbl_alarm_is_unlocked_and_the_stage_rehomed(dotshell_pm, serial_emulator):
    emu = serial_emulator("grbl", speed_deg_s=720.0)
    lines: list[str] = []
    h = handle(dotshell_pm, emu, "grbl", lines)
    emu.faults.alarm = True  # hard limit mid-move: ALARM:1, moves locked
    try:
        with_retries(lambda: h.move_to(90.0), 2, "move", EventBus())
    finally:
        h.shutdown()
    assert abs(emu.angle - 90.0) < 0.01
    assert any("unlocking ($X) and homing ($H)" in t for t in lines)
    sent = [c for _, c in emu.commands]
    assert sent.index("$X") < sent.index("$H") < len(sent) - 1


def test_garbage_never_sends_xon_xoff(serial_emulator, monkeypatch):
    from dotshell_serial.emulators.pty import NOT_NOISE

    emu = serial_emulator("zaber")
    emu.faults.garbage = True
    sent: list[bytes] = []
    write = os.write
    monkeypatch.setattr(os, "write", lambda fd, data: (sent.append(bytes(data)),
                                                       write(fd, data))[1])
    for _ in range(200):
        emu.send(b"x")
    monkeypatch.undo()
    noise = b"".join(chunk[:-1] for chunk in sent)
    assert len(noise) == 7 * 200 and not set(noise) & set(NOT_NOISE)


def test_check_connect_names_a_stuck_stage_instead_of_waiting_for_the_home_limit(
        tmp_path, serial_emulator, capsys, user_dirs):
    from stop_cases import zaber_profile
    from dotshell.cli.app import main

    emu = serial_emulator("zaber")
    emu.angle = 90.0
    emu.faults.stuck = True  # homing starts and never gets anywhere
    prof = zaber_profile(tmp_path, emu.port, "on_connect")
    assert main(["check", str(prof), "--connect"]) == 2  # home limit 300 s: the stall names it
    err = " ".join(capsys.readouterr().err.split())
    assert "homing is stuck — the device says it is moving but has stayed at 89.999°" in err
    assert "Traceback" not in err
    assert wait_for(lambda: not emu.moving, 5.0)
