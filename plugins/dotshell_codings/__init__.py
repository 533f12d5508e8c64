"""First-party pattern codings for dotshell (registered under the ``dotshell`` entry-point
group): ``graycode``, ``xor02``, ``xor04`` and ``graycode-phase``. See docs/codings.md."""

from dotshell import hookimpl
from dotshell.backends import Backend

from dotshell_codings.graycode import SETTINGS_SCHEMA, GrayCode, make_graycode
from dotshell_codings.phaseshift import SETTINGS_SCHEMA as PHASE_SETTINGS_SCHEMA
from dotshell_codings.phaseshift import GrayPhaseCode, make_gray_phase
from dotshell_codings.xor import XorCode, xor_factory

__all__ = ["GrayCode", "XorCode", "GrayPhaseCode", "make_graycode", "make_gray_phase",
           "xor_factory", "SETTINGS_SCHEMA", "PHASE_SETTINGS_SCHEMA", "dotshell_codings"]


@hookimpl
def dotshell_codings() -> list[Backend]:
    return [
        Backend(name="graycode", factory=make_graycode, settings_schema=SETTINGS_SCHEMA,
                summary="Gray code with inverse patterns, centred code and sub-pixel stripe "
                        "edges; contrast or robust (direct/global) bit classification"),
        Backend(name="xor02", factory=xor_factory(2), settings_schema=SETTINGS_SCHEMA,
                summary="XOR-02 code (Gupta et al. 2011): every pattern XOR the 2-px stripes, "
                        "robust to long-range global light"),
        Backend(name="xor04", factory=xor_factory(4), settings_schema=SETTINGS_SCHEMA,
                summary="XOR-04 code (Gupta et al. 2011): every pattern XOR the 4-px stripes, "
                        "robust to long-range global light"),
        Backend(name="graycode-phase", factory=make_gray_phase,
                settings_schema=PHASE_SETTINGS_SCHEMA,
                summary="Gray code + N-step phase shifting: continuous sub-pixel coordinates"),
    ]
