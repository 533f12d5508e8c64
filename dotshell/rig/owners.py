"""One owner at a time: a device (serial port, USB serial number, camera, framebuffer) is held by
one process, through an exclusive ``flock`` on a lock file that records who holds it (pid, host,
terminal, profile, since when; :mod:`dotshell.runtime.locks`).

The lock dies with its process (no stale state after a crash or ``kill -9``), and it is a lock,
not a ping: a holder that is momentarily unresponsive still holds it. Device lock files live in
``<runtime dir>/devices/`` (the rig servers' private runtime directory, see
:func:`dotshell.runtime.paths.runtime_dir`), named after the device's identity
(``dev_pts_3.lock`` for ``/dev/pts/3``).
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

from dotshell.errors import DeviceError
from dotshell.runtime.locks import OwnerLock, describe, holder

#: Settings whose value names the hardware a device opens (see :func:`device_identities`).
PATH_SETTINGS = ("port", "device", "source")


class DeviceInUse(DeviceError):
    """The device is held by another process (or another rig of this one)."""


def _path_identity(value: str) -> str | None:
    """The real path a device path or port spec names, or None if it names no device file."""
    from dotshell.rig.ports import BY_ID_DIR, resolve_port

    if value.startswith("serial:"):  # the port it is plugged into now, as a path would name it
        try:
            value = resolve_port(value)
        except DeviceError:  # not plugged in: connecting will say so
            return f"usb-serial:{value[len('serial:'):]}"
    if value.startswith("by-id:"):
        value = str(BY_ID_DIR / value[len("by-id:"):])
    if value.isdigit():  # an OpenCV camera index is /dev/videoN on Linux
        value = f"/dev/video{value}"
    if not value.startswith("/"):
        return None
    real = os.path.realpath(value)
    if os.path.isfile(real):  # a recording or a file-backed framebuffer: not hardware
        return None
    return real


def device_identities(settings: dict[str, Any]) -> list[str]:
    """What hardware a device's settings name: the real path of its ``port``/``device``/
    ``source`` (a serial port, /dev/videoN, a framebuffer) and its USB ``serial_number``;
    regular files (recordings) and simulated devices name none."""
    out = []
    for key in PATH_SETTINGS:
        value = settings.get(key)
        if isinstance(value, str) and value.strip():
            ident = _path_identity(value.strip())
            if ident is not None:
                out.append(ident)
    serial = settings.get("serial_number")
    if isinstance(serial, str) and serial.strip():
        out.append(f"usb-serial:{serial.strip()}")
    return sorted(set(out))


def device_lock_dir() -> Path:
    from dotshell.runtime.paths import runtime_dir  # the private runtime directory

    d = runtime_dir() / "devices"
    d.mkdir(mode=0o700, exist_ok=True)
    return d


def lock_name(identity: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]", "_", identity.strip("/")) + ".lock"


def profile_device_ids(profile: Any) -> dict[str, list[str]]:
    """What hardware each device role of ``profile`` (a :class:`~dotshell.profile.loader.Profile`)
    names (:func:`device_identities`), by role; roles that name none are left out."""
    from dotshell.profile.loader import DEVICE_ROLES

    out = {}
    for role in DEVICE_ROLES:
        section = profile.role(role)
        ids = device_identities(section["settings"]) if section else []
        if ids:
            out[role] = ids
    return out


def held_devices(device_ids: dict[str, list[str]]) -> list[tuple[str, str, dict[str, Any]]]:
    """(role, device, holder) of each device in ``device_ids`` (role: identities, as
    :func:`profile_device_ids` gives them) that another process holds now."""
    out = []
    for role, ids in device_ids.items():
        for ident in ids:
            info = holder(device_lock_dir() / lock_name(ident))
            if info is not None:
                out.append((role, ident, info))
    return out


class DeviceOwnership:
    """The device locks one rig holds, by role."""

    def __init__(self, profile: str) -> None:
        self.profile = profile
        self._locks: dict[str, list[OwnerLock]] = {}

    def claim(self, role: str, backend: str, settings: dict[str, Any]) -> None:
        """Hold every device the role's settings name, or raise :class:`DeviceInUse` naming
        the holder (nothing of this role is held then)."""
        if role in self._locks:
            return
        taken: list[OwnerLock] = []
        for ident in device_identities(settings):
            lock = OwnerLock(device_lock_dir() / lock_name(ident))
            other = lock.acquire({"profile": self.profile, "role": role, "backend": backend,
                                  "device": ident})
            if other is not None:
                for t in taken:
                    t.release()
                raise DeviceInUse(
                    f"{role} ({backend}): {ident} is held by {describe(other)} as its "
                    f"{other.get('role', 'device')}; one process drives a device at a time. "
                    "Stop that scan or server (dotshell stop PROFILE), or use another device.")
            taken.append(lock)
        self._locks[role] = taken

    def release(self, role: str | None = None) -> None:
        """Release the role's locks (every role's without ``role``)."""
        for r in [role] if role is not None else list(self._locks):
            for lock in self._locks.pop(r, []):
                lock.release()
