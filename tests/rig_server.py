"""A rig server for tests: a real :class:`RigServer` on a real Unix socket, run in a thread of
the test process (so tests can hold its Session and its bus), and the ``user_dirs`` fixture
that moves the user's directories (runtime, state, config) to a short private temporary
directory (import it into a test module to use it)."""

from __future__ import annotations

import shutil
import tempfile
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import pytest

from dotshell.session.console import Session
from dotshell.server.client import RemoteSession
from dotshell.runtime.paths import history_path, server_log_dir, socket_path
from dotshell.server.server import RigServer


@pytest.fixture
def user_dirs(monkeypatch) -> Iterator[Path]:
    """XDG_RUNTIME_DIR, XDG_STATE_HOME and XDG_CONFIG_HOME under a new directory in /tmp (a
    Unix socket path must stay under 108 bytes, pytest's tmp_path may not), removed after."""
    root = Path(tempfile.mkdtemp(prefix="ds-", dir="/tmp"))
    for var, sub in (("XDG_RUNTIME_DIR", "run"), ("XDG_STATE_HOME", "state"),
                     ("XDG_CONFIG_HOME", "config")):
        (root / sub).mkdir(mode=0o700)
        monkeypatch.setenv(var, str(root / sub))
    yield root
    shutil.rmtree(root, ignore_errors=True)


@contextmanager
def served(session: Session, name: str = "test", **options) -> Iterator[RigServer]:
    """``session`` served on a socket until the block ends (then stopped, its scan aborted)."""
    server = RigServer(session, socket_path(name), name=name, log_dir=server_log_dir(name),
                       history_file=history_path(), **options)
    server.start()
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield server
    finally:
        server.shutdown("test over", abort=True)
        server.wait(120)
        thread.join(10)


def attach(server: RigServer, client: str = "tui", control: bool = True) -> RemoteSession:
    return RemoteSession(server.socket_path, client=client, control=control)
