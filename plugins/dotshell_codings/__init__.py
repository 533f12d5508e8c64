"""First-party pattern codings for dotshell (registered under the ``dotshell`` entry-point
group): ``graycode``, ``xor02``, ``xor04`` and ``graycode-phase``. See docs/codings.md.

The backends are declared in ``dotshell.toml`` and built in :mod:`dotshell_codings.backends`:
this module imports no coding (the names below are imported on first access)."""

from __future__ import annotations

from dotshell import hookimpl
from dotshell.backends import Backend
from dotshell.manifest import backends_of, lazy_exports

__getattr__ = lazy_exports(__name__, {
    "GrayCode": "graycode:GrayCode", "make_graycode": "graycode:make_graycode",
    "SETTINGS_SCHEMA": "graycode:SETTINGS_SCHEMA", "XorCode": "xor:XorCode",
    "xor_factory": "xor:xor_factory", "GrayPhaseCode": "phaseshift:GrayPhaseCode",
    "make_gray_phase": "phaseshift:make_gray_phase",
    "PHASE_SETTINGS_SCHEMA": "phaseshift:SETTINGS_SCHEMA"})
__all__ = ["GrayCode", "XorCode", "GrayPhaseCode", "make_graycode", "make_gray_phase",
           "xor_factory", "SETTINGS_SCHEMA", "PHASE_SETTINGS_SCHEMA", "dotshell_codings"]


@hookimpl
def dotshell_codings() -> list[Backend]:
    """All codings, imported (when this package is registered as a plain pluggy plugin)."""
    return backends_of(__name__, "coding")
