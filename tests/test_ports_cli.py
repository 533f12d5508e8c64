"""`dotshell ports` and `dotshell emulate`, and profiles naming a port by by-id name or USB
serial number."""

import os
import subprocess
import sys
import time
from types import SimpleNamespace

import pytest
from rich.console import Console

from rig_server import user_dirs  # noqa: F401 (a fixture)
import dotshell.cli.devices as cli_devices
import dotshell.plugins
import dotshell.rig.ports as ports
from dotshell.cli.app import main
from dotshell.errors import DeviceError


def fake_comports(monkeypatch, entries):
    from serial.tools import list_ports

    monkeypatch.setattr(list_ports, "comports", lambda: [SimpleNamespace(
        device=device, vid=vid, pid=pid, serial_number=sn, manufacturer="", product="",
        description=desc) for device, vid, pid, sn, desc in entries])


def test_ports_lists_vid_pid_serial_by_id_and_the_matching_backend(monkeypatch, capsys,
                                                                   tmp_path):
    by_id = tmp_path / "by-id"
    by_id.mkdir()
    (by_id / "usb-Thorlabs_APT_55000123-if00-port0").symlink_to("/dev/ttyUSB3")
    monkeypatch.setattr(ports, "BY_ID_DIR", by_id)
    fake_comports(monkeypatch, [
        ("/dev/ttyUSB3", 0x0403, 0xFAF0, "55000123", "APT Stepper Motor Controller"),
        ("/dev/ttyACM0", 0x2341, 0x0043, "8573531303435", "Arduino Uno"),
        ("/dev/ttyUSB4", 0x0403, 0x6015, "DK0AHAJZ", "FT230X Basic UART"),
        ("/dev/ttyS0", None, None, None, "n/a")])
    monkeypatch.setattr(cli_devices, "out", Console(width=400, highlight=False))
    assert main(["ports"]) == 0
    rows = {line.split("│")[1].strip(): line for line in capsys.readouterr().out.splitlines()
            if line.startswith("│")}
    assert "0403:faf0" in rows["/dev/ttyUSB3"] and "55000123" in rows["/dev/ttyUSB3"]
    assert "stage:thorlabs-apt" in rows["/dev/ttyUSB3"]
    assert str(by_id / "usb-Thorlabs_APT_55000123-if00-port0") in rows["/dev/ttyUSB3"]
    assert "stage:grbl" in rows["/dev/ttyACM0"] and "analyzer:elliptec" in rows["/dev/ttyUSB4"]
    assert rows["/dev/ttyS0"].count(" - ") >= 3


def test_profiles_name_ports_by_usb_serial_number_and_by_id(monkeypatch, tmp_path, dotshell_pm,
                                                            serial_emulator):
    emu = serial_emulator("apt")
    by_id = tmp_path / "by-id"
    by_id.mkdir()
    (by_id / "usb-Thorlabs_K10CR1-if00").symlink_to(emu.pty_path)
    monkeypatch.setattr(ports, "BY_ID_DIR", by_id)
    fake_comports(monkeypatch, [(emu.pty_path, 0x0403, 0xFAF0, "55000123", "K10CR1")])
    for port in ("serial:55000123", "by-id:usb-Thorlabs_K10CR1-if00"):
        stage = dotshell_pm.create("stage", "thorlabs-apt", {"port": port})
        stage.connect()
        assert stage.identity().serial_number == "55000123" and stage.link.path
        stage.close()
    with pytest.raises(DeviceError, match=r"no serial port has USB serial number '999'; ports "
                       r"present: .*\(serial 55000123\)"):
        ports.resolve_port("serial:999", "thorlabs-apt")
    with pytest.raises(DeviceError, match="port /dev/nope does not exist; .*`dotshell ports`"):
        ports.resolve_port("/dev/nope", "grbl")


def test_emulate_prints_its_port_and_a_driver_talks_to_it(tmp_path, dotshell_pm):
    link = tmp_path / "zaber-link"
    proc = subprocess.Popen([sys.executable, "-m", "dotshell.cli.app", "emulate", "zaber", "--link",
                             str(link), "--seconds", "30"], stdout=subprocess.PIPE, text=True)
    try:
        first = proc.stdout.readline()
        assert first.startswith("zaber emulator on /dev/pts/")
        assert proc.stdout.readline().strip() == f"port for profiles: {link}"
        stage = dotshell_pm.create("stage", "zaber", {"port": str(link)})
        stage.connect()
        stage.move_to(12.5)
        assert stage.read_angle() == pytest.approx(12.5, abs=1e-3)
        stage.close()
    finally:
        proc.send_signal(2)
        out, _ = proc.communicate(timeout=10)
    assert proc.returncode == 0 and "commands received" in out and not link.exists()


def test_emulate_unknown_name_lists_the_emulators(capsys):
    assert main(["emulate", "lightcrafter-9000"]) == 2
    assert "installed emulators: apt, elliptec, grbl, switch, zaber" in capsys.readouterr().err


def test_ports_lists_running_emulators_and_vanish_after_counts_from_connect(
        tmp_path, dotshell_pm, capsys, monkeypatch, user_dirs):
    from stop_cases import wait_for

    link = tmp_path / "zaber-link"
    proc = subprocess.Popen([sys.executable, "-m", "dotshell.cli.app", "emulate", "zaber", "--link",
                             str(link), "--vanish-after", "0.3", "--seconds", "60"],
                            stdout=subprocess.PIPE, text=True)
    try:
        pty = proc.stdout.readline().split()[-1]
        assert proc.stdout.readline().strip() == f"port for profiles: {link}"
        monkeypatch.setattr(cli_devices, "out", Console(width=400, highlight=False))
        assert main(["ports"]) == 0
        listed = [line for line in capsys.readouterr().out.splitlines() if str(link) in line]
        assert len(listed) == 1 and pty in listed[0] and str(proc.pid) in listed[0]
        assert listed[0].rstrip(" │").endswith("-")  # nobody holds it yet
        stage = dotshell_pm.create("stage", "zaber", {"port": str(link)})
        stage.connect()  # no move: the port vanishes 0.3 s after this connect all the same
        assert wait_for(lambda: not link.exists(), 20.0)
        stage.close()
    finally:
        proc.send_signal(2)
        proc.communicate(timeout=10)
    assert main(["ports"]) == 0
    assert str(link) not in capsys.readouterr().out  # gone with its process


def test_ports_names_who_holds_an_emulators_port(tmp_path, dotshell_pm, serial_emulator, capsys,
                                                 monkeypatch, user_dirs):
    from stop_cases import zaber_profile
    from dotshell.profile.loader import load_profile
    from dotshell.rig.assembly import Rig

    emu = serial_emulator("zaber")
    fake_comports(monkeypatch, [(emu.pty_path, 0x2939, 0x495A, "33938", "Zaber X-MCB1")])
    monkeypatch.setattr(cli_devices, "out", Console(width=400, highlight=False))
    prof = zaber_profile(tmp_path, emu.port, "never")
    rig = Rig(load_profile(prof, dotshell_pm), dotshell_pm)
    rig.connect()
    try:
        assert main(["ports"]) == 0
    finally:
        rig.close()
    [row] = [line for line in capsys.readouterr().out.splitlines() if emu.pty_path in line]
    assert f"pid {os.getpid()}" in row and str(prof) in row and "as its stage" in row


def test_emulate_prints_its_models_errors(tmp_path, monkeypatch, capsys, user_dirs):
    import threading

    from stop_cases import wait_for
    from dotshell_serial.emulators.pty import LineEmulator

    class Broken(LineEmulator):
        name = "broken"

        def line(self, text):
            raise ZeroDivisionError(f"cannot parse {text!r}")

    monkeypatch.setattr(dotshell.plugins, "emulator_class", lambda name: Broken)
    link = tmp_path / "broken-link"

    def talk():
        assert wait_for(link.exists, 30.0)
        fd = os.open(link, os.O_RDWR | os.O_NOCTTY)
        os.write(fd, b"HELLO\n")
        os.close(fd)

    thread = threading.Thread(target=talk, daemon=True)
    thread.start()
    assert main(["emulate", "broken", "--link", str(link), "--seconds", "2"]) == 0
    thread.join(5)
    err = " ".join(capsys.readouterr().err.split())
    assert "emulator error: ZeroDivisionError: cannot parse 'HELLO'" in err
    assert "the port stays up" in err
