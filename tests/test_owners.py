"""One owner per device and per server (issues 28 and 33): a second rig, scan or server on
hardware already held is refused naming the holder (pid, terminal, profile); a server that does
not answer at the moment still holds its socket (a lock, not a ping), so a second `serve` never
deletes a live socket; `status` finds a server from any directory, by profile name or by the
profile file's identity."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from conftest import write_test_profile
from rig_server import served, user_dirs  # noqa: F401 (a fixture)
from stop_cases import zaber_profile
from dotshell.cli.app import main
from dotshell.session.console import Session
from dotshell.rig.owners import DeviceInUse, device_identities
from dotshell.runtime.locks import OwnerLock, server_lock_path
from dotshell.profile.loader import load_profile
from dotshell.rig.assembly import Rig
from dotshell.server.launch import locate
from dotshell.runtime.paths import history_path, server_log_dir, server_name, socket_path
from dotshell.server.protocol import ServerError
from dotshell.server.server import RigServer


def two_profiles(tmp_path: Path, port: str) -> tuple[Path, Path]:
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    return zaber_profile(tmp_path / "a", port, "never"), zaber_profile(tmp_path / "b", port,
                                                                       "never")


@pytest.fixture
def held(tmp_path, dotshell_pm, serial_emulator, user_dirs):
    """(emulator, first profile, second profile, a Rig of the first holding the stage)."""
    emu = serial_emulator("zaber")
    first, second = two_profiles(tmp_path, emu.port)
    holder = Rig(load_profile(first, dotshell_pm), dotshell_pm)
    holder.connect()
    yield emu, first, second, holder
    holder.close()


def test_a_second_rig_on_a_held_stage_is_refused_naming_the_holder(dotshell_pm, held):
    emu, first, second, holder = held
    try:
        other = Rig(load_profile(second, dotshell_pm), dotshell_pm)
        with pytest.raises(DeviceInUse) as info:
            other.connect()
        text = str(info.value)
        assert os.path.realpath(emu.port) in text and f"pid {os.getpid()}" in text
        assert str(first) in text and "terminal" in text and "stage" in text
        assert other.connected == [] and info.value.exit_code == 2
        received = len(emu.commands)
    finally:
        holder.close()
    assert len(emu.commands) == received  # the refused rig never talked to the stage
    other.connect()  # free again once the holder closed
    other.close()


def test_a_second_scan_on_a_held_stage_exits_2_naming_the_holder(tmp_path, held, capsys):
    emu, first, second, holder = held
    code = main(["scan", str(second), "--out", str(tmp_path / "runs")])
    err = " ".join(capsys.readouterr().err.split())
    assert code == 2 and "Traceback" not in err
    assert f"pid {os.getpid()}" in err and str(first) in err and "held by" in err


def test_a_second_server_on_a_held_stage_is_refused_naming_the_holder(tmp_path, dotshell_pm,
                                                                     held):
    emu, first, second, holder = held
    session = Session(second, pm=dotshell_pm, out_dir=tmp_path / "runs")
    try:
        sock = socket_path(server_name(second))
        server = RigServer(session, sock, name=sock.stem, log_dir=server_log_dir(sock.stem),
                           history_file=history_path())
        with pytest.raises(ServerError, match=rf"the profile's stage \({os.path.realpath(emu.port)}"
                                              rf"\) is held by pid {os.getpid()} .*profile "
                                              rf"{first}"):
            server.start()
        assert not sock.exists() and holder_free(sock)  # nothing left behind
    finally:
        session.close()
        holder.close()


def holder_free(sock: Path) -> bool:
    from dotshell.runtime.locks import holder as lock_holder

    return lock_holder(server_lock_path(sock)) is None


def test_a_port_named_by_usb_serial_number_is_the_port_it_is_plugged_into(monkeypatch):
    from serial.tools import list_ports

    monkeypatch.setattr(list_ports, "comports", lambda: [type("P", (), dict(
        device="/dev/null", vid=0x0403, pid=0xFAF0, serial_number="55000123", manufacturer="",
        product="", description="APT"))()])
    assert device_identities({"port": "serial:55000123"}) == \
        device_identities({"port": "/dev/null"}) == ["/dev/null"]


def test_device_identities_name_hardware_not_files(tmp_path):
    recording = tmp_path / "scan.mkv"
    recording.write_bytes(b"x")
    link = tmp_path / "tty"
    link.symlink_to("/dev/null")
    assert device_identities({"port": str(link), "device": 1}) == ["/dev/null"]
    assert device_identities({"source": str(recording)}) == []
    assert device_identities({"source": "2", "serial_number": "55000123"}) == \
        ["/dev/video2", "usb-serial:55000123"]
    assert device_identities({"port": "serial:NOT-PLUGGED-IN"}) == ["usb-serial:NOT-PLUGGED-IN"]


def test_a_silent_server_keeps_its_socket_and_a_second_server_is_refused(tmp_path, dotshell_pm,
                                                                        user_dirs):
    sock = socket_path("rig")
    # a server that holds its lock but does not answer at the moment (its socket refuses
    # connections, as a full accept backlog does to a ping)
    lock = OwnerLock(server_lock_path(sock))
    assert lock.acquire({"profile": "/lab/rig.toml", "name": "rig"}) is None
    sock.write_text("")  # its socket file, which a ping finds dead
    session = Session(write_test_profile(tmp_path), pm=dotshell_pm, out_dir=tmp_path / "runs")
    try:
        server = RigServer(session, sock, name="rig", log_dir=server_log_dir("rig"),
                           history_file=history_path())
        with pytest.raises(ServerError, match=rf"already runs on .*rig.sock: pid {os.getpid()} "
                                              r".*profile /lab/rig.toml"):
            server.start()
        assert sock.exists()  # not deleted
        assert main(["serve", "--socket", str(sock)]) == 2
        assert sock.exists()
    finally:
        session.close()
        lock.release()


def test_status_finds_a_server_from_any_directory(tmp_path, dotshell_pm, user_dirs, capsys,
                                                 monkeypatch):
    (tmp_path / "lab").mkdir()
    profile = write_test_profile(tmp_path / "lab", name="rig.toml")
    session = Session(profile, pm=dotshell_pm, out_dir=tmp_path / "runs")
    name = server_name(profile)
    try:
        with served(session, name=name) as server:
            elsewhere = tmp_path / "home"
            elsewhere.mkdir()
            monkeypatch.chdir(elsewhere)
            os.link(profile, elsewhere / "copy-of-rig.toml")  # the same file, another name
            for spelled in ("profiles/rig.toml", "rig", "copy-of-rig.toml", str(profile)):
                assert locate(spelled) == server.socket_path, spelled
            assert main(["status", "profiles/rig.toml"]) == 0
            shown = capsys.readouterr().out
            assert name in shown and "no rig server" not in shown
            assert main(["status"]) == 0
            assert name in capsys.readouterr().out
    finally:
        session.close()


def test_a_second_served_worker_on_a_held_stage_is_refused_naming_the_holder(tmp_path, held,
                                                                            capsys):
    """``dotshell serve`` runs its session in a worker process: the server refuses the held
    stage from the profile summary the worker sent, before it listens."""
    emu, first, second, holder = held
    sock = tmp_path / "second.sock"
    code = main(["serve", str(second), "--socket", str(sock)])
    err = " ".join(capsys.readouterr().err.split())
    assert code == 2 and "Traceback" not in err
    assert f"is held by pid {os.getpid()}" in err and str(first) in err
    assert not sock.exists() and holder_free(sock)
