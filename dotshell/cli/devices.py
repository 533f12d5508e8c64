"""``dotshell ports`` (what is plugged in, which backend fits it) and ``dotshell emulate NAME``
(a device's protocol emulator on a pseudo-terminal, for trying a driver without the device)."""

from __future__ import annotations

import argparse
import os
import time
from typing import Any, Callable

from rich.console import Console
from rich.markup import escape
from rich.table import Table

from dotshell.errors import PluginError

out = Console(highlight=False)
err = Console(stderr=True, highlight=False)


def _usb_devices() -> tuple[list[tuple[str, str]], str]:
    """(vid:pid, description) of every USB device pyusb sees, and a note if it cannot look."""
    try:
        import libusb_package
        import usb.core
    except ImportError as exc:
        return [], f"USB devices not listed: {exc}"
    try:
        found = list(libusb_package.find(find_all=True))
    except (usb.core.USBError, OSError, ValueError) as exc:
        return [], f"USB devices not listed: {exc}"
    rows = []
    for d in found:
        name = ""
        try:
            name = " ".join(x for x in (d.manufacturer, d.product) if x)
        except (usb.core.USBError, ValueError, NotImplementedError):
            pass  # strings need permission on some systems
        rows.append((f"{d.idVendor:04x}:{d.idProduct:04x}", name))
    return rows, ""


def cmd_ports(args: argparse.Namespace, pm_of: Callable[[argparse.Namespace], Any]) -> int:
    from dotshell.backends import ROLES
    from dotshell.rig.ports import list_serial_ports, matching_backends, running_emulators

    pm = pm_of(args)
    backends = {role: pm.backends(role) for role in ROLES}
    ports = list_serial_ports()
    t = Table(title="serial ports")
    for col in ("port", "by-id", "VID:PID", "serial number", "description", "backends",
                "held by"):
        t.add_column(col)
    for p in ports:
        t.add_row(p.device, escape(p.by_id or "-"), p.vid_pid or "-", escape(p.serial_number or "-"),
                  escape(p.description or "-"), escape(", ".join(matching_backends(p, backends))
                                                       or "-"), escape(_held_by(p.device)))
    out.print(t if ports else "no serial ports found")
    emulators = running_emulators()
    if emulators:
        e = Table(title="emulators (dotshell emulate)")
        for col in ("port for profiles", "pty", "emulator", "pid", "held by"):
            e.add_column(col)
        for info in emulators:
            e.add_row(escape(str(info.get("link", "-"))), escape(str(info.get("pty", "-"))),
                      escape(str(info.get("emulator", "-"))), str(info.get("pid", "-")),
                      escape(_held_by(str(info.get("pty", "")))))
        out.print(e)
    usb, note = _usb_devices()
    if usb:
        u = Table(title="USB devices")
        for col in ("VID:PID", "device", "backends"):
            u.add_column(col)
        for vid_pid, name in usb:
            fits = [f"{role}:{n}" for role, found in backends.items()
                    for n, info in sorted(found.items()) if vid_pid in info.usb_ids]
            u.add_row(vid_pid, escape(name or "-"), escape(", ".join(fits) or "-"))
        out.print(u)
    else:
        out.print(f"[dim]{escape(note or 'no USB devices found')}[/]")
    out.print("Name a port in a profile by path, by-id:NAME (stable across re-plugging) or "
              "serial:NUMBER (the USB serial number).")
    return 0


def _held_by(device: str) -> str:
    """Who holds the device at ``device`` (:mod:`dotshell.rig.owners`), or ``-``."""
    from dotshell.rig.owners import device_identities, device_lock_dir, lock_name
    from dotshell.runtime.locks import describe, holder

    for ident in device_identities({"port": device}) if device else []:
        info = holder(device_lock_dir() / lock_name(ident))
        if info is not None:
            return f"{describe(info)} as its {info.get('role', 'device')}"
    return "-"


def cmd_emulate(args: argparse.Namespace) -> int:
    from dotshell.plugins import emulator_class

    cls = emulator_class(args.name)
    link = args.link or f"/tmp/dotshell-emu-{args.name}"
    emu = cls(link=link, speed_deg_s=args.speed)
    for fault in args.fault:
        try:
            emu.set_fault(fault)
        except ValueError as exc:
            raise PluginError(f"{exc}.") from None
    emu.faults.vanish_after_connect_s = args.vanish_after
    emu.faults.return_after_s = args.return_after
    emu.start()
    listed = _list_emulator(args.name, emu)
    t0 = time.monotonic()
    out.print(f"{args.name} emulator on {emu.pty_path}", soft_wrap=True)
    out.print(f"port for profiles: {emu.port}", soft_wrap=True)
    out.print("Ctrl-C stops it.", soft_wrap=True)
    shown = 0
    try:
        while args.seconds <= 0 or time.monotonic() - t0 < args.seconds:
            time.sleep(0.1)
            shown = _show_errors(emu, shown)
    except KeyboardInterrupt:
        pass
    finally:
        emu.close()
        listed.release()
    _show_errors(emu, shown)
    out.print(f"{len(emu.commands)} commands received; port closed.")
    return 0


def _show_errors(emu: Any, shown: int) -> int:
    """Print the emulator's model errors not shown yet (an emulator bug never kills the port,
    so this is where it is seen); returns how many are shown."""
    for text in emu.errors[shown:]:
        err.print(f"[red]emulator error:[/] {escape(text)} (the port stays up; this is a bug "
                  "in the emulator's model)", soft_wrap=True)
    return len(emu.errors)


def _list_emulator(name: str, emu: Any) -> Any:
    """Record the running emulator (name, pty, link) under a lock in the runtime directory,
    for `dotshell ports`; the record dies with this process."""
    from dotshell.runtime.locks import OwnerLock
    from dotshell.rig.ports import emulator_dir

    lock = OwnerLock(emulator_dir() / f"{name}-{os.getpid()}.lock")
    lock.acquire({"emulator": name, "pty": emu.pty_path, "link": emu.port})
    return lock


def add_device_parsers(sub: Any, pm_of: Callable[[argparse.Namespace], Any]) -> None:
    """Register ``ports`` and ``emulate`` on the ``dotshell`` sub-command parser."""
    sp = sub.add_parser("ports", help="list serial and USB devices, with the backend that fits "
                        "each")
    sp.set_defaults(func=lambda args: cmd_ports(args, pm_of))

    sp = sub.add_parser("emulate", help="run a device's protocol emulator on a pseudo-terminal "
                        "(prints its port)")
    sp.add_argument("name", help="emulator: grbl, zaber, apt, elliptec, switch (and any a "
                    "plugin registers)")
    sp.add_argument("--link", help="stable path kept pointing at the pty (default "
                    "/tmp/dotshell-emu-NAME)")
    sp.add_argument("--speed", type=float, default=360.0, metavar="DEG_S",
                    help="simulated rotation speed in degrees per second (default 360)")
    sp.add_argument("--fault", action="append", default=[], metavar="NAME",
                    help="switch a fault on from the start (repeatable): error, silence, "
                    "garbage, stuck, alarm, or one the emulator defines")
    sp.add_argument("--vanish-after", type=float, metavar="S",
                    help="the port vanishes S seconds after the driver connects (its first "
                    "bytes)")
    sp.add_argument("--return-after", type=float, metavar="S",
                    help="...and comes back S seconds later (a re-plugged cable)")
    sp.add_argument("--seconds", type=float, default=0.0, help=argparse.SUPPRESS)
    sp.set_defaults(func=cmd_emulate)

