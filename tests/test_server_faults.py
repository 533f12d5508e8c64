"""The rig server under hostile input and hostile neighbours (issue 33): a client talks only to
a server of its own user (SO_PEERCRED), private files are private whatever the umask, and a
malformed, deeply nested or oversized protocol line gets an error reply or a close, never a
dead reader thread or a leaked connection."""

from __future__ import annotations

import json
import os
import socket
import stat
import threading

import pytest

from conftest import write_test_profile
from dotshell.session.console import Session
from dotshell.server.client import RemoteSession, ServerClient
from dotshell.runtime.paths import history_path, server_log_dir, state_dir
from dotshell.server.protocol import MAX_LINE, ServerError, decode
from dotshell.server.repl import ServerConsole
from rig_server import served, user_dirs  # noqa: F401 (a fixture)


@pytest.fixture
def session(tmp_path, pm, user_dirs):
    s = Session(write_test_profile(tmp_path, views=2), pm=pm, out_dir=tmp_path / "runs")
    yield s
    s.close()


# ---- a socket planted by another user ------------------------------------------------------------

IMPOSTOR = """
import socket, sys
s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
s.bind(sys.argv[1])
s.listen(1)
s.settimeout(60)
print("ready", flush=True)
conn, _ = s.accept()
conn.settimeout(10)
try:
    data = conn.recv(1024)
except OSError:
    data = b""
print(len(data), flush=True)
"""


def _other_python() -> str | None:
    """A Python another user may run (the system's; a venv under /root is not theirs)."""
    import shutil

    found = shutil.which("python3", path="/usr/bin:/bin")
    return found if found and os.stat(found).st_mode & 0o001 else None


@pytest.mark.skipif(os.geteuid() != 0 or _other_python() is None,
                    reason="needs root and a system python3 to listen as another user")
def test_a_client_never_talks_to_another_users_socket():
    """The docs' `--socket /tmp/rig.sock` planted by user nobody: the client refuses it
    before sending a byte (it used to list it in `status` and send it requests)."""
    import shutil
    import subprocess
    import tempfile

    d = tempfile.mkdtemp(prefix="ds-", dir="/tmp")
    os.chmod(d, 0o777)
    path = os.path.join(d, "rig.sock")
    try:
        proc = subprocess.Popen([_other_python(), "-c", IMPOSTOR, path], user=65534,
                                group=65534, stdout=subprocess.PIPE, text=True)
        assert proc.stdout.readline() == "ready\n"
        with pytest.raises(ServerError, match=r"runs as another user \(uid 65534"):
            ServerClient(path)
        out, _ = proc.communicate(timeout=60)
        assert out == "0\n"  # the impostor received nothing
    finally:
        shutil.rmtree(d, ignore_errors=True)


# ---- private files whatever the umask -------------------------------------------------------------

@pytest.mark.parametrize("umask", [0o022, 0o000])
def test_history_logs_and_state_folders_are_private_whatever_the_umask(umask, session,
                                                                       user_dirs):
    old = os.umask(umask)
    try:
        (user_dirs / "state" / "dotshell" / "servers").mkdir(parents=True, mode=0o755)
        (user_dirs / "state" / "dotshell").chmod(0o755)  # made open by an earlier version
        console = ServerConsole(session, lambda m: None, history_path())
        console.run("1 + 1")
        with served(session) as server:
            log = server.log_path
        modes = {p: stat.S_IMODE(p.stat().st_mode) for p in
                 (state_dir(), server_log_dir("test"), history_path(), log)}
    finally:
        os.umask(old)
    assert modes == {state_dir(): 0o700, server_log_dir("test"): 0o700, history_path(): 0o600,
                     log: 0o600}, {str(p): oct(m) for p, m in modes.items()}


# ---- hostile lines ----------------------------------------------------------------------------------

def test_a_deeply_nested_line_is_refused_not_fatal():
    with pytest.raises(ServerError, match="nested too deeply"):
        decode(b"[" * 250_000 + b"]" * 250_000)


def _raw(server) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.connect(str(server.socket_path))
    s.settimeout(60)
    return s


def _replies(s: socket.socket) -> list[dict]:
    """Every line the server sends until it closes the connection."""
    buf = b""
    while True:
        data = s.recv(65536)
        if not data:
            return [json.loads(line) for line in buf.splitlines() if line.strip()]
        buf += data


@pytest.mark.parametrize("line, says", [
    (b"[" * 250_000 + b"]" * 250_000 + b"\n", "nested too deeply"),
    (b"{not json\n", "not a protocol line"),
    (b"x" * (MAX_LINE + 70_000), f"longer than {MAX_LINE} bytes"),
], ids=["250k-deep JSON", "malformed", "oversized"])
def test_a_hostile_line_gets_an_error_reply_and_the_server_serves_on(session, line, says):
    with served(session) as server:
        s = _raw(server)
        s.sendall(line)
        if b"\n" in line:  # then the client leaves: the server must close, not leak, it
            s.shutdown(socket.SHUT_WR)
        replies = _replies(s)
        s.close()
        assert any(r.get("ok") is False and says in r.get("error", "") for r in replies), replies
        server_threads = [t for t in threading.enumerate() if t.name.startswith("dotshell-client-")]
        for t in server_threads:  # the connection's threads end (nothing leaks)
            t.join(30)
        assert not any(t.is_alive() for t in server_threads)
        tui = RemoteSession(server.socket_path, client="tui", control=False)
        assert tui.call("state")["state"]["server"]["pid"] == os.getpid()  # it still serves
        tui.close()
