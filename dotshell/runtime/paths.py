"""Where rig servers live: sockets in the user's runtime directory (``$XDG_RUNTIME_DIR/dotshell``,
else ``/tmp/dotshell-UID``, mode 0700), logs and console history in the state directory
(``$XDG_STATE_HOME/dotshell``, else ``~/.local/state/dotshell``), and the user's config file
(``$XDG_CONFIG_HOME/dotshell/config.toml``, else ``~/.config/dotshell/config.toml``); the state
and config directories are platformdirs' (the same places on Linux).

A server is named after its profile: the file's stem and 8 hex digits of its absolute path
(``sim-metal-cylinder-1a2b3c4d``), so ``dotshell tui PROFILE`` finds the server of that profile;
a server started without a profile is ``default``.
"""

from __future__ import annotations

import os
import re
import socket
import stat
import tempfile
import tomllib
from pathlib import Path
from typing import Any

import platformdirs

from dotshell.errors import DotshellError

#: Longest path a Unix-domain socket may have on Linux (sun_path is 108 bytes with the NUL).
MAX_SOCKET_PATH = 107
HANGUP_CHOICES = ("abort", "keep")


class ConfigError(DotshellError):
    """The user's config file is unreadable or has a wrong key or value."""


def runtime_dir() -> Path:
    """The private directory for server sockets (created 0700; refused if others can read it).

    Written here rather than by platformdirs: with ``$XDG_RUNTIME_DIR`` set both give
    ``$XDG_RUNTIME_DIR/dotshell``, but without it platformdirs falls back to
    ``/tmp/runtime-UID/dotshell`` (and warns), not to ``/tmp/dotshell-UID`` where the sockets of
    servers started by earlier versions are: they would no longer be found."""
    base = os.environ.get("XDG_RUNTIME_DIR")
    d = Path(base) / "dotshell" if base else Path(tempfile.gettempdir()) / f"dotshell-{os.getuid()}"
    d.mkdir(mode=0o700, parents=True, exist_ok=True)
    st = d.stat()
    if st.st_uid != os.getuid() or stat.S_IMODE(st.st_mode) & 0o077:
        raise DotshellError(f"{d} belongs to another user or is open to others (mode "
                            f"{stat.S_IMODE(st.st_mode):o}); remove it or set XDG_RUNTIME_DIR to a "
                            "private directory.")
    return d


def state_dir() -> Path:
    """The directory for server logs and the console history (created on demand, 0700
    whatever the umask: it holds typed code and paths)."""
    return private_dir(Path(platformdirs.user_state_dir("dotshell")))


def private_dir(d: Path) -> Path:
    """``d`` made (with its parents) and set to mode 0700 whatever the umask, also when an
    earlier version made it open to others."""
    d.mkdir(mode=0o700, parents=True, exist_ok=True)
    if stat.S_IMODE(d.stat().st_mode) != 0o700:
        d.chmod(0o700)
    return d


def open_private(path: Path, mode: str = "a") -> Any:
    """``path`` opened for text (``a`` or ``w``, UTF-8, line-buffered) with mode 0600 whatever
    the umask, also when an earlier version made it open to others."""
    flags = os.O_WRONLY | os.O_CREAT | (os.O_APPEND if mode == "a" else os.O_TRUNC)
    fd = os.open(path, flags | os.O_CLOEXEC, 0o600)
    os.fchmod(fd, 0o600)
    return os.fdopen(fd, mode, encoding="utf-8", buffering=1)


def config_path() -> Path:
    """The user's config file (platformdirs' config directory of dotshell)."""
    return Path(platformdirs.user_config_dir("dotshell")) / "config.toml"


def user_config() -> dict[str, Any]:
    """The user's config with defaults filled in: ``profile_dirs`` (list of paths the TUI's
    profile picker also lists) and ``server.on_hangup`` (``abort`` or ``keep``)."""
    path = config_path()
    raw: dict[str, Any] = {}
    if path.is_file():
        try:
            raw = tomllib.loads(path.read_text(encoding="utf-8"))
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise ConfigError(f"{path}: {exc}; fix or remove the file.") from None
    unknown = set(raw) - {"profile_dirs", "server"} | set(raw.get("server", {})) - {"on_hangup"}
    if unknown:
        raise ConfigError(f"{path}: unknown key(s) {', '.join(sorted(unknown))}; known are "
                          "profile_dirs and [server] on_hangup (docs/server.md).")
    dirs = raw.get("profile_dirs", [])
    if not isinstance(dirs, list) or not all(isinstance(d, str) for d in dirs):
        raise ConfigError(f"{path}: profile_dirs must be a list of directory paths.")
    hangup = raw.get("server", {}).get("on_hangup", "abort")
    if hangup not in HANGUP_CHOICES:
        raise ConfigError(f"{path}: [server] on_hangup = {hangup!r}; choose one of "
                          f"{', '.join(HANGUP_CHOICES)}.")
    return {"profile_dirs": [Path(d).expanduser() for d in dirs],
            "server": {"on_hangup": hangup}}


def server_name(profile: str | Path | None) -> str:
    """The name of the server for a profile file (``default`` without one)."""
    if profile is None:
        return "default"
    from dotshell.shipped import resolve

    p = resolve("profiles", profile).resolve()  # a bare name may be a shipped profile
    stem = re.sub(r"[^A-Za-z0-9_.-]", "_", p.stem)[:40]
    import hashlib  # at first use: 9 ms of every start-up

    return f"{stem}-{hashlib.sha1(str(p).encode()).hexdigest()[:8]}"


def socket_path(name: str) -> Path:
    path = runtime_dir() / f"{name}.sock"
    if len(os.fsencode(path)) > MAX_SOCKET_PATH:
        raise DotshellError(f"the socket path {path} is longer than {MAX_SOCKET_PATH} bytes; "
                            "set XDG_RUNTIME_DIR to a shorter directory.")
    return path


def server_log_dir(name: str) -> Path:
    return private_dir(state_dir() / "servers" / name)


def history_path() -> Path:
    """The console history every server of this user shares (JSON lines, newest last)."""
    return state_dir() / "console_history.jsonl"


def alive(path: Path) -> bool:
    """True when a server answers on the socket (a stale socket file is not alive)."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(2.0)
    try:
        s.connect(os.fspath(path))
        return True
    except OSError:
        return False
    finally:
        s.close()


def running_servers() -> list[Path]:
    """Sockets of the servers that hold their lock (:mod:`dotshell.runtime.locks`: found even
    while momentarily unresponsive) or answer, sorted by name."""
    from dotshell.runtime.locks import held_servers

    d = runtime_dir()
    held = {sock for sock, _ in held_servers(d)}
    return sorted(held | {p for p in d.glob("*.sock") if p not in held and alive(p)})
