"""Stop is unconditional (issue 28): Ctrl-C, SIGTERM and SIGHUP stop the stage while it homes
at connect, while a move hangs and while a refused move is retried (the Zaber emulator on a pty
stops moving), and the process ends within the stated bound; a failed motion is stopped before
it is retried; a device whose call is still inside its driver is never closed, reconnected or
homed under it (it is marked lost, naming the plugin), and closing the rig returns within
``STOP_WAIT_S`` even with a driver that never returns."""

from __future__ import annotations

import threading

import pytest

from stop_cases import EXIT_BOUND_S, SIGNALS, signal_scan, wait_for
from dotshell.backends import RigContext
from dotshell.errors import DeviceError, DeviceLostError
from dotshell.rig.handles import DeviceHandle, DevicePolicy


@pytest.mark.parametrize("case,signame", [("homing", "SIGINT"), ("homing", "SIGTERM"),
                                          ("hung move", "SIGTERM"), ("retry", "SIGINT")])
def test_signal_stops_the_stage_and_the_scan_ends_within_the_bound(tmp_path, serial_emulator,
                                                                   case, signame):
    emu = serial_emulator("zaber", speed_deg_s=10.0)
    result = signal_scan(tmp_path, emu, case, SIGNALS[signame])
    assert result.stop_s is not None, (case, result.commands[-10:], result.stderr)
    # the stage stops moving: its position no longer changes (the emulator halts on `stop`)
    assert wait_for(lambda: not emu.moving, 5.0), (case, emu.angle)
    assert result.exit_s is not None, f"{case}: still running {EXIT_BOUND_S} s after {signame}"
    assert result.exit_code == 130, result.stderr
    assert "Traceback" not in result.stderr
    if case == "homing":
        assert 1.0 < emu.angle < 89.0  # stopped on its way from 90° to 0°
    if case == "retry":
        # the refused move was followed by a stop before the move was sent again
        texts = [c.split(maxsplit=3)[-1] for _, c in result.commands]
        first, second = [i for i, c in enumerate(texts) if c.startswith("move abs")][:2]
        assert "stop" in texts[first + 1:second], texts


def test_ctrl_c_while_check_connect_homes_stops_the_stage(tmp_path, serial_emulator):
    emu = serial_emulator("zaber", speed_deg_s=10.0)
    result = signal_scan(tmp_path, emu, "homing", SIGNALS["SIGINT"], command="check")
    assert result.stop_s is not None, (result.commands[-10:], result.stderr)
    assert wait_for(lambda: not emu.moving, 5.0) and 1.0 < emu.angle < 89.0
    assert result.exit_s is not None and result.exit_code == 130, result.stderr


class HangingStage:
    """A stage driver whose move_to never returns, whatever it is told (a driver hung in C)."""

    def __init__(self) -> None:
        self.calls: list[str] = []
        self.inside = threading.Event()
        self.release = threading.Event()

    def connect(self) -> None:
        self.calls.append("connect")

    def close(self) -> None:
        self.calls.append("close")

    def status(self) -> dict:
        return {}

    def stop(self) -> None:
        self.calls.append("stop")

    def home(self) -> None:
        self.calls.append("home")

    def move_to(self, degrees: float) -> None:
        self.calls.append("move_to")
        self.inside.set()
        self.release.wait()


def hanging_handle(timeout_s: float = 0.2) -> tuple[DeviceHandle, HangingStage]:
    dev = HangingStage()
    h = DeviceHandle("stage", "hangs", "hang-plugin", "dotshell-hang", dev, RigContext(),
                     DevicePolicy(timeouts_s={"move_to": timeout_s}, home="on_connect"))
    h.connect()
    return h, dev


def test_a_timed_out_move_is_stopped_and_the_device_lost_not_reconnected():
    h, dev = hanging_handle()
    try:
        with pytest.raises(DeviceLostError, match=r"plugin 'hang-plugin' \(dotshell-hang\) is "
                                                  r"still inside move_to\(\).*left alone"):
            h.move_to(10.0)
        assert "stop" in dev.calls and dev.calls.count("connect") == 1
        # a reconnect (a session's connect on a lost device) refuses while the call runs
        with pytest.raises(DeviceLostError, match="still inside move_to"):
            h.reopen()
        assert "close" not in dev.calls and "home" not in dev.calls
        assert dev.calls.count("connect") == 1
    finally:
        dev.release.set()
        h.release()


def test_closing_a_rig_with_a_hung_driver_returns_without_closing_under_the_call():
    h, dev = hanging_handle(timeout_s=3600.0)
    def move() -> None:
        try:
            h.move_to(10.0)
        except DeviceError:
            pass

    mover = threading.Thread(target=move, daemon=True)
    mover.start()
    assert dev.inside.wait(30.0)
    done = threading.Event()
    closer = threading.Thread(target=lambda: (h.shutdown(), done.set()), daemon=True)
    closer.start()
    try:
        assert done.wait(60.0), "shutdown waited for the hung driver"
        assert "stop" in dev.calls and "close" not in dev.calls
        assert h.lost
    finally:
        dev.release.set()


def test_a_refused_move_is_stopped_before_it_is_retried(serial_emulator, dotshell_pm):
    from dotshell.pipeline.acquire import with_retries
    from dotshell.events import EventBus

    emu = serial_emulator("zaber", speed_deg_s=720.0)
    emu.faults.error = 1
    ctx = RigContext().for_device("stage", "zaber")
    info = dotshell_pm.backend("stage", "zaber")
    dev = dotshell_pm.create("stage", "zaber", {"port": emu.port}, ctx)
    h = DeviceHandle("stage", "zaber", info.plugin, info.distribution, dev, ctx, DevicePolicy())
    h.connect()
    try:
        with_retries(lambda: h.move_to(45.0), 2, "move", EventBus())
    finally:
        h.shutdown()
    texts = [c.split(maxsplit=3)[-1] for _, c in emu.commands]
    moves = [i for i, c in enumerate(texts) if c.startswith("move abs")]
    assert len(moves) == 2 and "stop" in texts[moves[0] + 1:moves[1]], texts
    assert abs(emu.angle - 45.0) < 0.01


def test_a_device_error_from_a_motion_is_not_mistaken_for_a_user_stop():
    class Refuses(HangingStage):
        def move_to(self, degrees: float) -> None:
            self.calls.append("move_to")
            raise DeviceError("refused")

    dev = Refuses()
    h = DeviceHandle("stage", "refuses", "p", "d", dev, RigContext(), DevicePolicy())
    h.connect()
    with pytest.raises(DeviceError, match="refused") as info:
        h.move_to(1.0)
    assert type(info.value) is DeviceError and dev.calls[-1] == "stop"
    h.shutdown()


def test_sigterm_ends_a_scan_whose_driver_hangs_in_move_to_within_the_bound(tmp_path):
    from stop_cases import hung_driver_scan

    exit_s, code, err = hung_driver_scan(tmp_path, SIGNALS["SIGTERM"])
    assert exit_s is not None, f"still running {EXIT_BOUND_S} s after SIGTERM"
    assert code == 130 and "Traceback" not in err, err
