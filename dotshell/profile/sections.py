"""The core sections of a profile as typed, frozen objects (``profile.scan.views``, ...).

:func:`~dotshell.profile.loader.load_profile` builds them once from the validated dict, so
every field here exists and holds a value of its schema's type (defaults filled in). A
field is named as its TOML key (units in the name: ``_mm``, ``_deg``, ``_ms``, ``_px``);
lists become tuples so that a section cannot be changed behind the profile's back. The
meaning of every key is in :data:`~dotshell.profile.loader.SCHEMA` and docs/profiles.md.

Backend roles (``[camera]``, ``[coding]``, ...) and ``[export.NAME]`` hold a plugin's own
settings; they stay plain mappings (:meth:`Profile.role`, :attr:`Profile.export`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from collections.abc import Iterator, Mapping
from typing import Any, ClassVar, TypeVar

S = TypeVar("S", bound="Section")


def _frozen(value: Any) -> Any:
    if isinstance(value, list):
        return tuple(_frozen(v) for v in value)
    return value


@dataclass(frozen=True)
class Section(Mapping[str, Any]):
    """Base of the typed sections: built from a validated table by :meth:`from_table`.

    A section is also a read-only mapping of its TOML keys (``section["views"]``,
    ``dict(section)``), so code written against the raw tables (third-party plugins, helpers
    that also read a run's recorded profile.toml) takes it unchanged; new code reads
    attributes.
    """

    #: fields that are sub-tables, with the class each is built as
    nested: ClassVar[dict[str, type[Section]]] = {}

    @classmethod
    def from_table(cls: type[S], table: Mapping[str, Any]) -> S:
        """The section of a validated table (every key of the schema present)."""
        values = {}
        for f in dataclasses.fields(cls):
            raw = table[f.name]
            sub = cls.nested.get(f.name)
            values[f.name] = sub.from_table(raw) if sub is not None else _frozen(raw)
        return cls(**values)

    def __getitem__(self, key: str) -> Any:
        if key not in self._keys():
            raise KeyError(key)
        return getattr(self, key)

    def __iter__(self) -> Iterator[str]:
        return iter(self._keys())

    def __len__(self) -> int:
        return len(self._keys())

    def _keys(self) -> tuple[str, ...]:
        return tuple(f.name for f in dataclasses.fields(self))

    def as_table(self) -> dict[str, Any]:
        """The section as a plain dict (sub-sections as dicts, lists for tuples), e.g. to merge
        command-line options into and validate again."""
        return {f.name: _thawed(getattr(self, f.name)) for f in dataclasses.fields(self)}


@dataclass(frozen=True)
class ProfileInfo(Section):
    """``[profile]``: the profile's name (in run directory names) and a line for humans."""

    name: str
    description: str


@dataclass(frozen=True)
class ScanSettings(Section):
    """``[scan]``: the views, exposure and acquisition of a scan."""

    views: int  #: views equally spaced over 360 degrees (when angles_deg is empty)
    angles_deg: tuple[float, ...]  #: explicit stage angles (degrees); override views
    exposure_ms: float  #: camera exposure (ms)
    settle_ms: float  #: wait after each projector change (ms)
    retries: int  #: re-tries of a failed capture, re-captures of a view failing checks
    frame_checks: bool  #: check each view's frames against what was projected
    acquisition: str  #: "auto" | "sequenced" | "show-capture"
    pattern_period_ms: float  #: sequenced: time per pattern (ms); 0 = shortest possible
    pdi: bool  #: polarization difference imaging
    pdi_angles_deg: tuple[float, ...]  #: analyzer angles (parallel, perpendicular), degrees

    def view_angles_deg(self) -> list[float]:
        """Stage angles of the views in degrees: angles_deg, else views spread over 360°."""
        if self.angles_deg:
            return list(self.angles_deg)
        return [360.0 * i / self.views for i in range(self.views)]


@dataclass(frozen=True)
class RoiSettings(Section):
    """``[processing.roi]``: the region kept around the turntable axis (mm)."""

    radius_mm: float  #: keep points within this distance of the axis
    z_min_mm: float  #: drop points below this height above the plate
    z_max_mm: float  #: drop points above this height


@dataclass(frozen=True)
class ProcessingSettings(Section):
    """``[processing]``: reconstruction filters."""

    nested: ClassVar[dict[str, type[Section]]] = {"roi": RoiSettings}

    roi: RoiSettings
    row_tolerance_px: float  #: max reprojection error from decoded column and row (pixels)
    max_depth_jump_mm: float  #: speckle filter threshold (mm); 0 = off
    min_ray_angle_deg: float  #: drop points whose camera and projector rays meet at less


@dataclass(frozen=True)
class ValidationSettings(Section):
    """``[validation]``: the sample's known shape, for the accuracy report."""

    shape: str  #: "none" | "cylinder"
    radius_mm: float  #: true radius (mm)
    height_mm: float  #: true height (mm)
    edge_margin_mm: float  #: band left out at the top and bottom edges (mm)
    cell_deg: float  #: coverage cell width around the axis (degrees)
    cell_mm: float  #: coverage cell height (mm)


@dataclass(frozen=True)
class OutputsSettings(Section):
    """``[outputs]``: previews written into the run."""

    previews: bool  #: render PNG previews
    preview_view: int  #: the view shown in frame previews


@dataclass(frozen=True)
class OpticsSettings(Section):
    """``[mesh.optics]``: optical properties written for every node."""

    mua_per_mm: float  #: absorption coefficient μa (1/mm)
    musp_per_mm: float  #: reduced scattering coefficient μs' (1/mm)
    refractive_index: float  #: refractive index n


@dataclass(frozen=True)
class OptodesSettings(Section):
    """``[mesh.optodes]``: sources and detectors (mm, sample frame) and their links."""

    sources_mm: tuple[tuple[float, ...], ...]  #: [[x, y, z], ...] (mm)
    detectors_mm: tuple[tuple[float, ...], ...]  #: [[x, y, z], ...] (mm)
    links: tuple[tuple[int, ...], ...]  #: [[source, detector], ...]; empty = all pairs


@dataclass(frozen=True)
class MeshSettings(Section):
    """``[mesh]``: surface and volume meshing of the cloud."""

    nested: ClassVar[dict[str, type[Section]]] = {"optics": OpticsSettings,
                                                   "optodes": OptodesSettings}

    after_scan: bool  #: mesh at the end of scan / reconstruct
    node_distance_mm: float  #: target distance between mesh nodes (mm)
    also_node_distances_mm: tuple[float, ...]  #: further node distances (mm)
    close_bottom: bool  #: close the open bottom at bottom_z_mm
    bottom_z_mm: float  #: height of the closing plane above the plate (mm)
    previews: bool  #: render surface and volume previews
    optics: OpticsSettings
    optodes: OptodesSettings


@dataclass(frozen=True)
class TransilluminationSettings(Section):
    """``[transillumination]``: trans-illumination capture at the scan's views."""

    enabled: bool  #: capture trans-illumination frames
    exposure_ms: float  #: exposure of the trans-illumination, dark and flat frames (ms)
    targets_mm: tuple[tuple[float, ...], ...]  #: [lateral, height] source positions (mm)
    views: tuple[int, ...]  #: the scan's views to trans-illuminate; empty = all
    dark: bool  #: also capture a frame with the source off and subtract it
    flat_field: str  #: "capture" | "none" | an image file relative to the profile


@dataclass(frozen=True)
class NormalizeSettings(Section):
    """``[normalize]``: intensity normalization on the surface."""

    after_scan: bool  #: normalize at the end of a scan with trans-illumination frames
    min_sin_beta: float  #: nodes seen more grazing than this are masked
    compare: tuple[str, ...]  #: further normalizer backends reported side by side
    saturation_fraction: float  #: share of full scale counted as saturated
    max_normal_spread_deg: float  #: crease mask threshold (degrees)
    max_cloud_distance_mm: float  #: unscanned mask threshold (mm)
    min_pixels: float  #: nodes covered by fewer (hat-weighted) camera pixels are masked


@dataclass(frozen=True)
class CalibrationSource(Section):
    """``[calibration]``: where the scan's calibration comes from."""

    source: str  #: "file" | "ground-truth"
    file: str  #: calibration.json, relative to the profile


@dataclass(frozen=True)
class CalibrateSettings(Section):
    """``[calibrate]``: the target and poses of ``dotshell calibrate`` (docs/calibration.md)."""

    target: str  #: "checkerboard" | "charuco"
    columns: int  #: squares across the board
    rows: int  #: squares down the board
    square_mm: float  #: side of a square (mm)
    marker_mm: float  #: ChArUco marker side (mm)
    dictionary: str  #: ArUco dictionary name
    exposure_ms: float  #: exposure for the target frames (ms)
    distortion: str  #: lens model solved for
    min_poses: int  #: fewest good poses a solve accepts
    outlier_factor: float  #: pose RMS above this many times the median is left out
    max_rms_px: float  #: pose / solve RMS limit (pixels)
    max_sigma_pct: float  #: a solve's one-sigma limit (% of the value)
    warn_sigma_pct: float  #: one-sigma above which a parameter is named poorly determined (%)
    max_blur_px: float  #: edges wider than this mark a pose blurred (pixels)
    window: float  #: local-homography window half-size (fraction of corner spacing)
    poses: tuple[tuple[float, ...], ...]  #: [roll, tilt, pan (deg), x, y, z (mm)] rows
    turntable_angles_deg: tuple[float, ...]  #: stage angles for the axis (degrees)
    turntable_pose: tuple[float, ...]  #: board pose on the stage for the axis


def _thawed(value: Any) -> Any:
    if isinstance(value, Section):
        return value.as_table()
    if isinstance(value, tuple):
        return [_thawed(v) for v in value]
    return value


#: section name in the TOML file → its class (the attribute of Profile is the same name,
#: except ``[profile]`` → ``Profile.info``)
SECTIONS: dict[str, type[Section]] = {
    "profile": ProfileInfo, "scan": ScanSettings, "processing": ProcessingSettings,
    "validation": ValidationSettings, "outputs": OutputsSettings, "mesh": MeshSettings,
    "transillumination": TransilluminationSettings, "normalize": NormalizeSettings,
    "calibration": CalibrationSource, "calibrate": CalibrateSettings,
}
