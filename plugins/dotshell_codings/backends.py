"""The codings' backends, each built on first use (``python_name`` targets of this package's
``dotshell.toml``): importing this module imports no coding."""

from __future__ import annotations

from dotshell.backends import Backend


def graycode() -> Backend:
    from dotshell_codings.graycode import SETTINGS_SCHEMA, make_graycode

    return Backend("graycode", make_graycode, SETTINGS_SCHEMA)


def xor02() -> Backend:
    from dotshell_codings.xor import SETTINGS_SCHEMA, xor_factory

    return Backend("xor02", xor_factory(2), SETTINGS_SCHEMA)


def xor04() -> Backend:
    from dotshell_codings.xor import SETTINGS_SCHEMA, xor_factory

    return Backend("xor04", xor_factory(4), SETTINGS_SCHEMA)


def graycode_phase() -> Backend:
    from dotshell_codings.phaseshift import SETTINGS_SCHEMA, make_gray_phase

    return Backend("graycode-phase", make_gray_phase, SETTINGS_SCHEMA)
