"""The serial devices' backends, each built on first use (``python_name`` targets of this
package's ``dotshell.toml``): importing this module imports no driver (nor pyserial)."""

from __future__ import annotations

import importlib
from typing import Any

from dotshell.backends import Backend


def _driver(name: str, module: str, cls: str, schema: str) -> Backend:
    """The backend ``name``: class ``cls`` of ``dotshell_serial.<module>``, built with
    ``(settings, context)``, its settings ``schema``."""
    mod = importlib.import_module(f"dotshell_serial.{module}")
    driver = getattr(mod, cls)

    def make(settings: dict[str, Any], context: Any = None) -> Any:
        return driver(settings, context)

    make.__name__ = f"make_{cls}"
    return Backend(name, make, getattr(mod, schema))


def grbl() -> Backend:
    return _driver("grbl", "grbl", "GrblStage", "GRBL_SCHEMA")


def zaber() -> Backend:
    return _driver("zaber", "zaber", "ZaberStage", "ZABER_SCHEMA")


def thorlabs_apt() -> Backend:
    return _driver("thorlabs-apt", "apt", "AptRotationStage", "APT_SCHEMA")


def elliptec() -> Backend:
    return _driver("elliptec", "elliptec", "ElliptecAnalyzer", "ELLIPTEC_SCHEMA")


def serial_switch() -> Backend:
    return _driver("serial-switch", "switch", "SerialSwitch", "SWITCH_SCHEMA")
