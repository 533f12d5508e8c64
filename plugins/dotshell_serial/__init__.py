"""dotshell_serial — real serial devices and their protocol emulators.

Registered under the ``dotshell`` entry-point group as ``serial = "dotshell_serial"``, exactly
like a third-party plugin. Backends:

* stages: ``grbl`` (GRBL v1.1 controllers), ``zaber`` (Zaber ASCII rotary stages),
  ``thorlabs-apt`` (Thorlabs APT/Kinesis rotation mounts, K10CR1 class);
* analyzer: ``elliptec`` (Thorlabs Elliptec ELL14 class rotation mount);
* light source: ``serial-switch`` (any text-controlled on/off switch).

Emulators of each device on a real pseudo-terminal are in :mod:`dotshell_serial.emulators`
(``dotshell emulate NAME``).

Public API for third-party serial drivers (docs/writing-a-device-plugin.md, section 5):
:class:`dotshell_serial.link.SerialLink` (a port as a driver uses it),
:class:`dotshell_serial.base.SerialDevice` (connect/handshake/close, status, identity, stop flag)
with :func:`~dotshell_serial.base.port_settings`, :func:`~dotshell_serial.base.motion_settings`
and :class:`~dotshell_serial.base.MotionWatch`; :class:`dotshell_serial.emulators.pty.PtyEmulator`
and :class:`~dotshell_serial.emulators.pty.LineEmulator` (a device's far end on a pty); and
:func:`dotshell_serial.protocol.scripted` (request/reply exchanges, no pty).
"""

from __future__ import annotations

from dotshell import hookimpl
from dotshell.backends import Backend

from dotshell_serial.apt import APT_SCHEMA, AptRotationStage
from dotshell_serial.elliptec import ELLIPTEC_SCHEMA, ElliptecAnalyzer
from dotshell_serial.grbl import GRBL_SCHEMA, GrblStage
from dotshell_serial.switch import SWITCH_SCHEMA, SerialSwitch
from dotshell_serial.zaber import ZABER_SCHEMA, ZaberStage

from dotshell_serial.base import MotionWatch, SerialDevice, motion_settings, port_settings
from dotshell_serial.link import SerialLink

__all__ = ["AptRotationStage", "ElliptecAnalyzer", "GrblStage", "MotionWatch", "SerialDevice",
           "SerialLink", "SerialSwitch", "ZaberStage", "motion_settings", "port_settings"]

#: USB ids (vid:pid): Arduino Uno/Mega and their CH340/FTDI clones; Zaber's own and FTDI
#: bridges; Thorlabs APT controllers (FTDI with Thorlabs' product id); Elliptec buses (FT230X).
ARDUINO_IDS = ("2341:0043", "2341:0001", "2341:0010", "2341:0042", "1a86:7523", "0403:6001")
ZABER_IDS = ("2939:495a", "0403:6001")
APT_IDS = ("0403:faf0",)
ELLIPTEC_IDS = ("0403:6015",)


def _factory(cls):
    def make(settings: dict, context=None):
        return cls(settings, context)

    make.__name__ = f"make_{cls.__name__}"
    return make


@hookimpl
def dotshell_stages() -> list[Backend]:
    return [
        Backend("grbl", _factory(GrblStage), GRBL_SCHEMA,
                "GRBL v1.1 controller turning a rotation axis set up in degrees ($H homing, "
                "feed-hold stop)", usb_ids=ARDUINO_IDS),
        Backend("zaber", _factory(ZaberStage), ZABER_SCHEMA,
                "Zaber rotary stage, ASCII protocol (X-RSW, X-RST, RSB)", usb_ids=ZABER_IDS),
        Backend("thorlabs-apt", _factory(AptRotationStage), APT_SCHEMA,
                "Thorlabs APT/Kinesis rotation mount over its FTDI serial port (K10CR1 class)",
                usb_ids=APT_IDS),
    ]


@hookimpl
def dotshell_analyzers() -> list[Backend]:
    return [Backend("elliptec", _factory(ElliptecAnalyzer), ELLIPTEC_SCHEMA,
                    "Thorlabs Elliptec rotation mount (ELL14 class) turning the PDI analyzer",
                    usb_ids=ELLIPTEC_IDS)]


@hookimpl
def dotshell_light_sources() -> list[Backend]:
    return [Backend("serial-switch", _factory(SerialSwitch), SWITCH_SCHEMA,
                    "any light source switched on/off by text commands over a serial port")]
