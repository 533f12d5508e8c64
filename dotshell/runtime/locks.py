"""One owner at a time, for any process: an exclusive ``flock`` on a lock file that records who
holds it (pid, host, terminal, command, since when, and what the owner adds), and the rig
servers' locks (one server per name, found by its lock).

The lock dies with its process (no stale state after a crash or ``kill -9``), and it is a lock,
not a ping: a holder that is momentarily unresponsive still holds it. Devices are held through
these locks by :mod:`dotshell.rig.owners`, runs by :mod:`dotshell.run.lifecycle`.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import socket
import sys
import time
from pathlib import Path
from typing import Any


def terminal() -> str:
    """This process's terminal (``/dev/pts/4``) or ``no terminal``."""
    for fd in (0, 1, 2):
        try:
            if os.isatty(fd):
                return os.ttyname(fd)
        except OSError:
            continue
    return "no terminal"


def describe(info: dict[str, Any]) -> str:
    """A holder as people read it: ``pid 1234 (dotshell serve, terminal /dev/pts/4, profile
    /lab/rig.toml, since 2026-12-05T21:30:00)``."""
    if not info:
        return "another process (it did not say who)"
    parts = [info.get("command") or "dotshell", f"terminal {info.get('tty', '?')}",
             f"profile {info.get('profile') or 'none'}", f"since {info.get('since', '?')}"]
    host = info.get("host")
    where = f" on {host}" if host and host != socket.gethostname() else ""
    return f"pid {info.get('pid', '?')}{where} ({', '.join(parts)})"


def _command() -> str:
    """``dotshell scan``, ``dotshell serve``, ... (what this process was started as)."""
    args = sys.argv[1:2]
    return "dotshell " + args[0] if args and not args[0].startswith("-") else "dotshell"


def read_info(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(Path(path).read_text() or "{}")
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def try_flock(fd: int) -> bool:
    """An exclusive, non-blocking ``flock`` on ``fd``: True when taken; False when another
    open file holds it (``fd`` is then closed)."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return True
    except OSError as exc:
        os.close(fd)
        if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            raise
        return False


class OwnerLock:
    """An exclusive, non-blocking ``flock`` on ``path`` whose file says who holds it."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        self._fd: int | None = None

    def acquire(self, info: dict[str, Any]) -> dict[str, Any] | None:
        """Take the lock and record ``info`` (pid, host, terminal and time added); None when
        taken, else what the holder recorded (``{}`` if it recorded nothing yet)."""
        if self._fd is not None:
            return None
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
        if not try_flock(fd):
            return read_info(self.path)
        record = {"pid": os.getpid(), "host": socket.gethostname(), "tty": terminal(),
                  "command": _command(),
                  "since": time.strftime("%Y-%m-%dT%H:%M:%S"), **info}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(record).encode(), 0)
        self._fd = fd
        return None

    def release(self) -> None:
        if self._fd is None:
            return
        fd, self._fd = self._fd, None
        try:
            os.ftruncate(fd, 0)
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)

    @property
    def held(self) -> bool:
        return self._fd is not None


def holder(path: Path | str) -> dict[str, Any] | None:
    """Who holds the lock file ``path`` (``{}`` if unknown), None when nobody does."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:
        return read_info(Path(path))
    else:
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


# ---- rig servers --------------------------------------------------------------------------------

def server_lock_path(sock: Path | str) -> Path:
    """The lock file of the server listening on ``sock`` (next to it: ``NAME.sock.lock``)."""
    sock = Path(sock)
    return sock.with_name(sock.name + ".lock")


def profile_identity(profile: str | Path | None) -> dict[str, Any]:
    """How a server's profile is found again from any directory: its absolute path, its name
    (the file's stem) and the file's identity (device and inode numbers)."""
    if profile is None:
        return {"profile": None, "profile_name": None, "profile_file": None}
    p = Path(profile).expanduser().resolve()
    try:
        st = p.stat()
        file_id: list[int] | None = [st.st_dev, st.st_ino]
    except OSError:
        file_id = None
    return {"profile": str(p), "profile_name": p.stem, "profile_file": file_id}


def held_servers(directory: Path) -> list[tuple[Path, dict[str, Any]]]:
    """(socket, holder) of every server whose lock in ``directory`` is held, by socket name —
    found by the lock, so a server that is momentarily unresponsive is still listed."""
    out = []
    for lock in sorted(directory.glob("*.sock.lock")):
        info = holder(lock)
        if info is not None:
            out.append((lock.with_name(lock.name[:-len(".lock")]), info))
    return out


def servers_of_profile(directory: Path, profile: str | Path) -> list[tuple[Path, dict[str, Any]]]:
    """The held servers of ``profile``: the same file (device and inode) when ``profile`` is a
    file here, else the same profile name (``rig`` or ``profiles/rig.toml`` from a directory
    where no such file is: the stem ``rig``)."""
    wanted = profile_identity(profile)
    name = Path(profile).stem
    found = []
    for sock, info in held_servers(directory):
        if wanted["profile_file"] is not None:
            if info.get("profile_file") == wanted["profile_file"]:
                found.append((sock, info))
        elif info.get("profile_name") == name:
            found.append((sock, info))
    return found
