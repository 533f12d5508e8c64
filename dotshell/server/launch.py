"""Finding the rig server a command means, and starting one in the background.

A started server runs ``dotshell serve`` in a new session (no controlling terminal, so a
dropped SSH connection never reaches it), with stdin from /dev/null and its output appended to
``server.out`` in its state directory.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from dotshell.runtime.paths import alive, running_servers, server_log_dir, server_name, socket_path
from dotshell.server.protocol import ServerError
from dotshell.shipped import resolve

#: How long a new server may take to listen (seconds): imports, plugins, the profile, the rig.
START_TIMEOUT_S = 120.0


def locate(profile: str | Path | None = None, name: str | None = None,
           sock: str | Path | None = None) -> Path | None:
    """The socket a command means: ``sock``, else the server ``name``, else the server of
    ``profile``, else the only running server (None when none runs; ServerError when several
    do and nothing says which)."""
    if sock is not None:
        return Path(sock)
    if name is not None:
        return socket_path(name)
    if profile is not None:
        return _profile_socket(profile)
    running = running_servers()
    if len(running) > 1:
        names = ", ".join(p.stem for p in running)
        raise ServerError(f"several rig servers run ({names}); name one with --server NAME or "
                          "give its profile.")
    return running[0] if running else None


def _profile_socket(profile: str | Path) -> Path:
    """The socket of ``profile``'s server from any directory: its own name if that server
    runs, else the running server of the same file (device and inode) or, where no such file
    is, of the same profile name; else where its server would listen."""
    from dotshell.runtime.locks import holder, server_lock_path, servers_of_profile

    own = socket_path(server_name(profile))
    if holder(server_lock_path(own)) is not None:
        return own
    found = servers_of_profile(own.parent, profile)
    if len(found) > 1:
        names = ", ".join(f"{sock.stem} ({info.get('profile')})" for sock, info in found)
        raise ServerError(f"several rig servers run a profile named {Path(profile).stem} "
                          f"({names}); name one with --server NAME or give the profile's path.")
    return found[0][0] if found else own


@dataclass
class Starting:
    """A ``dotshell serve`` process started by :func:`spawn_server`, not yet listening."""

    proc: subprocess.Popen[bytes]
    sock: Path
    out_file: Path


def start_server(profile: str | Path | None, *, sock: Path, out: str | Path,
                 overrides: list[str] | tuple[str, ...] = (), exit_when_idle: bool = True,
                 strict_plugins: bool = False) -> int:
    """Start ``dotshell serve`` detached on ``sock`` and wait until it answers; returns its pid.
    ServerError (with the end of its output) when it exits or does not answer in time."""
    return wait_listening(spawn_server(profile, sock=sock, out=out, overrides=overrides,
                                       exit_when_idle=exit_when_idle,
                                       strict_plugins=strict_plugins))


def spawn_server(profile: str | Path | None, *, sock: Path, out: str | Path,
                 overrides: list[str] | tuple[str, ...] = (), exit_when_idle: bool = True,
                 strict_plugins: bool = False) -> Starting:
    """Start ``dotshell serve`` detached on ``sock`` without waiting for it (the caller may
    do its own start-up meanwhile, then :func:`wait_listening`)."""
    name = sock.stem
    out_file = server_log_dir(name) / "server.out"
    cmd = [sys.executable, "-m", "dotshell.cli.app", *(["--strict-plugins"] if strict_plugins else []),
           "serve", *([str(resolve("profiles", profile).resolve())] if profile else []),
           "--out", str(Path(out).expanduser().resolve()), "--socket", str(sock),
           *[arg for o in overrides for arg in ("--set", o)],
           *(["--exit-when-idle"] if exit_when_idle else [])]
    with open(out_file, "ab") as f:
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=f, stderr=subprocess.STDOUT,
                                start_new_session=True, close_fds=True, cwd=os.getcwd())
    return Starting(proc, sock, out_file)


def wait_listening(starting: Starting) -> int:
    """Wait until a spawned server answers on its socket; returns its pid. ServerError (with
    the end of its output) when it exits or does not answer within START_TIMEOUT_S."""
    proc, sock, out_file = starting.proc, starting.sock, starting.out_file
    t0 = time.monotonic()
    while not alive(sock):
        code = proc.poll()
        if code is not None or time.monotonic() - t0 > START_TIMEOUT_S:
            if code is None:
                proc.terminate()
            tail = out_file.read_text(errors="replace")[-2000:].strip()
            why = f"exit code {code}" if code is not None else f"no answer in {START_TIMEOUT_S} s"
            raise ServerError(f"the rig server did not start ({why}); its output ({out_file}):"
                              f"\n{tail}")
        time.sleep(0.1)
    return proc.pid
