"""`dotshell tui` in a real terminal: started under a pseudo-terminal (pexpect, with the screen
kept by the pyte terminal emulator) and, where tmux is installed, inside tmux — it draws,
takes keys and quits cleanly."""

import os
import shlex
import shutil
import subprocess
import sys
import time
import uuid

import pexpect
import pyte
import pytest

from conftest import small_profile_dict, write_profile

COLS, ROWS = 80, 24


def write_test_profile(tmp_path):
    raw = small_profile_dict(factor=0.12, views=2)
    raw["camera"]["settings"]["supersample"] = 1
    raw["outputs"] = {"previews": False}
    return write_profile(tmp_path / "p.toml", raw)


def tui_command(tmp_path):
    return [sys.executable, "-m", "dotshell.cli", "tui", str(write_test_profile(tmp_path)),
            "--out", str(tmp_path / "runs")]


class PtyScreen:
    """A child process on a pty and the screen it has drawn."""

    def __init__(self, argv, cwd):
        env = {**os.environ, "TERM": "xterm-256color"}
        env.pop("COLUMNS", None)
        env.pop("LINES", None)
        self.child = pexpect.spawn(argv[0], argv[1:], cwd=str(cwd), env=env,
                                   dimensions=(ROWS, COLS))
        self.screen = pyte.Screen(COLS, ROWS)
        self.stream = pyte.ByteStream(self.screen)
        self.raw = b""

    def pump(self, seconds=0.1):
        try:
            data = self.child.read_nonblocking(65536, timeout=seconds)
        except pexpect.TIMEOUT:
            return
        except pexpect.EOF:
            return
        self.raw += data
        self.stream.feed(data)

    def text(self):
        return "\n".join(self.screen.display)

    def wait_for(self, needle, timeout_s=60.0):
        t0 = time.monotonic()
        while needle not in self.text():
            assert self.child.isalive(), f"the TUI exited early:\n{self.text()}"
            assert time.monotonic() - t0 < timeout_s, f"{needle!r} never shown:\n{self.text()}"
            self.pump()


def test_tui_under_a_pty_draws_takes_keys_and_quits_cleanly(tmp_path):
    term = PtyScreen(tui_command(tmp_path), tmp_path)
    try:
        term.wait_for("sim-turntable")
        assert "Rig" in term.screen.display[1] + term.screen.display[2]  # the tab bar
        t0 = time.monotonic()  # the footer on the last row (drawn after the panes)
        while "Quit" not in term.screen.display[ROWS - 1] and time.monotonic() - t0 < 10:
            term.pump()
        assert "Quit" in term.screen.display[ROWS - 1], "\n".join(term.screen.display)
        term.child.send("c")
        term.wait_for("connected")
        term.child.send("\x1b[C")  # → : jog by +5°
        term.wait_for("angle 5.00°")
        term.child.send("\x11")  # ctrl+q
        t0 = time.monotonic()
        while term.child.isalive():
            assert time.monotonic() - t0 < 30, "the TUI did not quit"
            term.pump()
        term.pump()
    finally:
        if term.child.isalive():
            term.child.terminate(force=True)
    term.child.close()
    assert term.child.exitstatus == 0
    assert b"\x1b[?1049h" in term.raw and b"\x1b[?1049l" in term.raw  # alt screen left again


@pytest.mark.skipif(shutil.which("tmux") is None, reason="tmux is not installed")
def test_tui_inside_tmux(tmp_path):
    sock = f"dotshell-test-{uuid.uuid4().hex[:8]}"

    def tmux(*args, check=True):
        return subprocess.run(["tmux", "-L", sock, "-f", os.devnull, *args], check=check,
                              capture_output=True, text=True)

    def screen():
        return tmux("capture-pane", "-p", "-t", "tui", check=False).stdout

    def wait_for(needle, timeout_s=60.0):
        t0 = time.monotonic()
        while needle not in screen():
            assert time.monotonic() - t0 < timeout_s, f"{needle!r} never shown:\n{screen()}"
            time.sleep(0.1)

    command = shlex.join(tui_command(tmp_path)) + f"; echo exit=$? > {tmp_path / 'status'}"
    tmux("new-session", "-d", "-s", "tui", "-x", str(COLS), "-y", str(ROWS),
         "-e", "TERM=screen-256color", command)
    try:
        wait_for("sim-turntable")
        tmux("send-keys", "-t", "tui", "c")
        wait_for("connected")
        tmux("send-keys", "-t", "tui", "Right")
        wait_for("angle 5.00°")
        tmux("send-keys", "-t", "tui", "C-q")
        t0 = time.monotonic()
        while not (tmp_path / "status").is_file():
            assert time.monotonic() - t0 < 30, f"the TUI did not quit:\n{screen()}"
            time.sleep(0.1)
        assert (tmp_path / "status").read_text().strip() == "exit=0"
    finally:
        tmux("kill-server", check=False)
