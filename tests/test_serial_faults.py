"""Every serial backend against its emulator, through every fault switch: the user gets one
paragraph naming the device, its port, the command and a fix (exit code 2), or — for line
noise — the call succeeds and a warning goes to the run's log."""

import pytest

from dotshell.backends import RigContext
from dotshell.errors import DeviceError, DeviceLostError, DeviceTimeout
from dotshell.rig.handles import DeviceHandle, DevicePolicy

#: emulator, role, backend, the call, what its message names, per fault: (error, text)
BACKENDS = {
    "grbl": ("stage", "grbl", lambda d: d.move_to(90.0), {
        "error": (DeviceError, r"GRBL refused 'G90 G0 X90.0000' with error:9 \(G-code is locked "
                               r"out .*home with \$H or unlock with \$X"),
        "alarm": (DeviceError, r"ALARM:1 — hard limit triggered; .*home \(\$H\)"),
        "stuck": (DeviceTimeout, r"the move to 90° did not finish in time .*feed hold.*raise "
                                 r"\[stage.timeouts\] move_to"),
    }),
    "zaber": ("stage", "zaber", lambda d: d.move_to(90.0), {
        "error": (DeviceError, r"rejected 'move abs 384000' \(BADDATA: the value is out of "
                               r"range"),
        "alarm": (DeviceError, r"fault FS during the position query \(stalled and stopped — "
                               r"something blocks the stage\); fix the cause"),
        "stuck": (DeviceTimeout, r"the move to 90° did not finish in time.*raise "
                                 r"\[stage.timeouts\] move_to"),
    }),
    "apt": ("stage", "thorlabs-apt", lambda d: d.move_to(90.0), {
        "error": (DeviceError, r"reported error 10 \(move rejected: motor not enabled\) about "
                               r"message 0x0453 during the move to 90°; .*fix the cause"),
        "alarm": (DeviceError, r"stopped the move to 90° at 45.000° \(forward \(CW\) hardware "
                               r"limit\); clear the limit and home"),
        "stuck": (DeviceTimeout, r"the move to 90° did not finish in time .*MOT_MOVE_STOP.*raise "
                                 r"\[stage.timeouts\] move_to"),
    }),
    "elliptec": ("analyzer", "elliptec", lambda d: d.set_angle(90.0), {
        "error": (DeviceError, r"answered the move to 90° with status 2 \(mechanical time-out "
                               r"\(the mount is blocked or needs cleaning"),
        "alarm": (DeviceError, r"answered the move to 90° with status 2 \(mechanical time-out"),
        "stuck": (DeviceTimeout, r"did not report the end of the move.*raise "
                                 r"\[analyzer.timeouts\] set_angle"),
        # a move is answered only when it ends, so silence looks like a move that never ends
        "silence": (DeviceTimeout, r"no reply to the move to 90° \('ma00008C00'\); .*Check "
                                   r"power and cable"),
    }),
    "switch": ("light_source", "serial-switch", lambda d: d.set(True), {
        "error": (DeviceError, r"answered 'ON' \(switch on\) with 'ERR 3 interlock open'; "
                               r"check its interlock"),
    }),
}
SILENT = (DeviceTimeout, r"no reply to .* within 0.3 s.*Check that the .* is powered and "
                         r"connected")
LOST = (DeviceLostError, r"the port failed while .*unplugged, powered off or reset.*reconnect = "
                         r"false")
CASES = [(emu, fault) for emu, (_, _, _, faults) in BACKENDS.items()
         for fault in sorted({*faults, "silence", "garbage", "vanish"})]


def connected(pm, emu, role, backend, timeout_s=1.5):
    ctx = RigContext().for_device(role, backend)
    lines = []
    ctx.log.listen(lambda level, text, when: lines.append((level, text)))
    info = pm.backend(role, backend)
    dev = pm.create(role, backend, {"port": emu.port, "reply_timeout_s": 0.3}, ctx)
    h = DeviceHandle(role, backend, info.plugin, info.distribution, dev, ctx,
                     DevicePolicy(timeouts_s={"move_to": timeout_s, "set_angle": timeout_s},
                                  reconnect=False))
    h.connect()
    return h, lines


@pytest.mark.parametrize("name,fault", CASES)
def test_fault_gives_one_paragraph_naming_device_port_command_and_fix(dotshell_pm, serial_emulator,
                                                                      name, fault):
    role, backend, call, faults = BACKENDS[name]
    emu = serial_emulator(name, speed_deg_s=180.0)
    dev, lines = connected(dotshell_pm, emu, role, backend)
    if fault == "vanish":
        if role == "light_source":
            emu.unplug()
        else:
            emu.faults.vanish_after_s = 0.1
    elif fault == "alarm":
        emu.faults.alarm = True
    else:
        setattr(emu.faults, fault, True)
    if fault == "garbage":
        call(dev)
        assert any(level == "warning" and f"noise on {emu.port}" in text for level, text in lines)
        return
    kind, text = faults.get(fault) or {"silence": SILENT, "vanish": LOST}[fault]
    with pytest.raises(kind, match=text) as info:
        call(dev)
    message = str(info.value)
    assert str(emu.port) in message and "\n" not in message and info.value.exit_code == 2
    dev.shutdown()


def test_every_backend_is_driven_through_every_fault_switch():
    from dotshell_serial.emulators.pty import Faults

    for name, (role, _, _, faults) in BACKENDS.items():
        covered = {f for n, f in CASES if n == name}
        relevant = set(Faults.NAMES) if role != "light_source" else {"error", "silence",
                                                                    "garbage", "vanish"}
        assert relevant <= covered, name
