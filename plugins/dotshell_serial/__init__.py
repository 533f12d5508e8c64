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

The backends are declared in ``dotshell.toml`` (with the USB ids ``dotshell ports`` matches) and
built in :mod:`dotshell_serial.backends`: this module imports no driver and not pyserial (the
names below are imported on first access).
"""

from __future__ import annotations

from dotshell import hookimpl
from dotshell.backends import Backend
from dotshell.manifest import backends_of, lazy_exports

__all__ = ["AptRotationStage", "ElliptecAnalyzer", "GrblStage", "MotionWatch", "SerialDevice",
           "SerialLink", "SerialSwitch", "ZaberStage", "motion_settings", "port_settings"]
__getattr__ = lazy_exports(__name__, {
    "AptRotationStage": "apt:AptRotationStage", "ElliptecAnalyzer": "elliptec:ElliptecAnalyzer",
    "GrblStage": "grbl:GrblStage", "SerialSwitch": "switch:SerialSwitch",
    "ZaberStage": "zaber:ZaberStage", "MotionWatch": "base:MotionWatch",
    "SerialDevice": "base:SerialDevice", "motion_settings": "base:motion_settings",
    "port_settings": "base:port_settings", "SerialLink": "link:SerialLink"})

# The hooks below serve when this package is registered as a plain pluggy plugin; the plugin
# manager reads dotshell.toml instead and imports a backend only when it is used.


@hookimpl
def dotshell_stages() -> list[Backend]:
    return backends_of(__name__, "stage")


@hookimpl
def dotshell_analyzers() -> list[Backend]:
    return backends_of(__name__, "analyzer")


@hookimpl
def dotshell_light_sources() -> list[Backend]:
    return backends_of(__name__, "light_source")
