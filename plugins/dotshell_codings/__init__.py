"""First-party pattern codings for dotshell (registered under the ``dotshell`` entry-point
group). Provides the ``graycode`` coding backend."""

from dotshell import hookimpl
from dotshell.backends import Backend

from dotshell_codings.graycode import SETTINGS_SCHEMA, GrayCode, make_graycode

__all__ = ["GrayCode", "make_graycode", "SETTINGS_SCHEMA", "dotshell_codings"]


@hookimpl
def dotshell_codings() -> list[Backend]:
    return [Backend(
        name="graycode",
        factory=make_graycode,
        settings_schema=SETTINGS_SCHEMA,
        summary="Gray code with inverse patterns, centred code and sub-pixel stripe edges",
    )]
