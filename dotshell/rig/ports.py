"""Serial port discovery and naming: what is plugged in, which backend fits it, and which port a
profile means. Used by ``dotshell ports`` and by serial drivers (any plugin may use it).

Profiles may name a port three ways (``[stage.settings] port = ...``):

* a path: ``/dev/ttyUSB0``, ``COM3``, or a pyserial URL (``socket://host:port``);
* the stable udev name: ``by-id:usb-FTDI_FT230X_Basic_UART_DK0AHAJZ-if00-port0`` or the full
  ``/dev/serial/by-id/...`` path (survives re-plugging and reboots);
* the USB serial number: ``serial:55000123`` (a Thorlabs APT controller's serial, an FTDI
  chip's ``D30AB1CD``, ...).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from dotshell.errors import DeviceError

BY_ID_DIR = Path("/dev/serial/by-id")


@dataclass(frozen=True)
class SerialPortInfo:
    """One serial port as the operating system reports it.

    Attributes:
        device: the path to open (``/dev/ttyUSB0``).
        by_id: its ``/dev/serial/by-id`` path, if udev made one.
        vid, pid: USB vendor and product id (None for non-USB ports).
        serial_number: the USB serial number string, if any.
        manufacturer, product, description: as reported.
    """

    device: str
    by_id: str = ""
    vid: int | None = None
    pid: int | None = None
    serial_number: str = ""
    manufacturer: str = ""
    product: str = ""
    description: str = ""

    @property
    def vid_pid(self) -> str:
        """``"0403:faf0"`` (lower-case hex), or ``""`` for non-USB ports."""
        return "" if self.vid is None or self.pid is None else f"{self.vid:04x}:{self.pid:04x}"


def _by_id_links() -> dict[str, str]:
    """Real device path → its /dev/serial/by-id path."""
    links: dict[str, str] = {}
    if BY_ID_DIR.is_dir():
        for link in sorted(BY_ID_DIR.iterdir()):
            try:
                links[os.path.realpath(link)] = str(link)
            except OSError:
                continue
    return links


def list_serial_ports() -> list[SerialPortInfo]:
    """Every serial port the system reports (pyserial's ``list_ports``), with by-id names."""
    from serial.tools import list_ports

    links = _by_id_links()
    out = []
    for p in list_ports.comports():
        out.append(SerialPortInfo(
            device=p.device, by_id=links.get(os.path.realpath(p.device), ""), vid=p.vid,
            pid=p.pid, serial_number=p.serial_number or "", manufacturer=p.manufacturer or "",
            product=p.product or "", description=p.description or ""))
    return out


def _available(ports: list[SerialPortInfo]) -> str:
    if not ports:
        return "no serial ports are present"
    return "ports present: " + "; ".join(
        p.device + (f" (serial {p.serial_number})" if p.serial_number else "")
        + (f" = {p.by_id}" if p.by_id else "") for p in ports)


def resolve_port(spec: str, device: str = "device") -> str:
    """The path to open for a profile's ``port`` value (see the module docstring); a
    DeviceError naming the ports there are when nothing matches."""
    spec = spec.strip()
    if not spec:
        raise DeviceError(f"{device}: no port is set; add port = \"/dev/ttyUSB0\" (or "
                          "\"serial:NUMBER\", \"by-id:NAME\") to its settings; `dotshell "
                          "ports` lists what is plugged in.")
    if spec.startswith("serial:"):
        number = spec[len("serial:"):]
        ports = list_serial_ports()
        for p in ports:
            if p.serial_number == number:
                return p.device
        raise DeviceError(f"{device}: no serial port has USB serial number {number!r}; "
                          f"{_available(ports)}. Is it plugged in and powered?")
    if spec.startswith("by-id:"):
        spec = str(BY_ID_DIR / spec[len("by-id:"):])
    if "://" in spec or os.path.exists(spec) or spec.upper().startswith("COM"):
        return spec
    raise DeviceError(f"{device}: port {spec} does not exist; {_available(list_serial_ports())}. "
                      "Plug the device in, or fix the port (`dotshell ports`).")


def matching_backends(port: SerialPortInfo, backends: dict[str, dict[str, object]]) -> list[str]:
    """``role:backend`` names whose :attr:`~dotshell.backends.Backend.usb_ids` list this port's
    VID:PID (``backends`` is ``{role: {name: BackendInfo}}``)."""
    vp = port.vid_pid
    if not vp:
        return []
    return [f"{role}:{name}" for role, found in backends.items()
            for name, info in sorted(found.items())
            if vp in getattr(info, "usb_ids", ())]


def emulator_dir() -> Path:
    """Where running ``dotshell emulate`` processes record themselves (private runtime dir)."""
    from dotshell.runtime.paths import runtime_dir  # the private runtime directory

    d = runtime_dir() / "emulators"
    d.mkdir(mode=0o700, exist_ok=True)
    return d


def running_emulators() -> list[dict[str, object]]:
    """What each running ``dotshell emulate`` recorded (``emulator``, ``pty``, ``link``,
    ``pid``), found by its held lock, sorted by link."""
    from dotshell.runtime.locks import holder

    found = [holder(p) for p in sorted(emulator_dir().glob("*.lock"))]
    return sorted((i for i in found if i), key=lambda i: str(i.get("link")))
