"""Hardware and scan profiles (TOML): which backend fills each role, the scan, processing,
validation and outputs. See ``docs/profiles.md`` for every key.

:func:`load_profile` validates the whole file — core sections against :data:`SCHEMA` and each
backend's settings against the schema its plugin declares — and raises
:class:`~dotshell.errors.ProfileError` naming the file, the key path, the bad value and the
valid choices.
"""

from __future__ import annotations

import copy
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dotshell.profile.calibration import CALIBRATE_SCHEMA
from dotshell.errors import ProfileError
from dotshell.profile.mesh import MESH_SCHEMA
from dotshell.plugins import PluginManager
from dotshell.profile.sections import (CalibrateSettings, CalibrationSource,
                                       MeshSettings, NormalizeSettings, OutputsSettings,
                                       ProcessingSettings, ProfileInfo, ScanSettings,
                                       TransilluminationSettings, ValidationSettings)
from dotshell.settings import REQUIRED, Setting, validate_settings
from dotshell.profile.transillum import NORMALIZE_SCHEMA, TRANSILLUMINATION_SCHEMA

DEVICE_ROLES = ("camera", "projector", "stage", "analyzer", "light_source")
REQUIRED_ROLES = ("camera", "projector", "stage", "coding")
#: Default timeout of each device call in seconds (``[ROLE.timeouts]``, used by
#: :mod:`dotshell.rig.handles`); ``other`` covers every method not listed.
TIMEOUT_DEFAULTS_S: dict[str, float] = {
    "connect": 30.0, "close": 10.0, "status": 5.0, "capture": 30.0, "show": 10.0,
    "move_to": 120.0, "set_angle": 60.0, "home": 300.0, "set": 10.0, "read_angle": 10.0,
    "other": 30.0,
}


def _role(required: bool) -> Setting:
    return Setting("table", default=REQUIRED if required else None, schema={
        "backend": Setting("str", help="name of the backend (see `dotshell plugins`)"),
        "settings": Setting("table", default={}, help="the backend's own settings"),
    }, help="backend filling this role")


def _device_role(required: bool, homing: bool = False) -> Setting:
    """A device role's section: the backend, its settings, and how the rig treats the device."""
    schema = {
        "backend": Setting("str", help="name of the backend (see `dotshell plugins`)"),
        "settings": Setting("table", default={}, help="the backend's own settings"),
        "timeouts": Setting("table", default={}, help="seconds each device call may take before "
                            "it fails with a DeviceTimeout (docs/devices.md)", schema={
            name: Setting("float", None, f"{name}() (default {s:g} s)" if name != "other" else
                          f"any other call (default {s:g} s)", "s", min=0.001)
            for name, s in TIMEOUT_DEFAULTS_S.items()}),
        "reconnect": Setting("bool", default=True, help="reopen the device once when it is "
                             "lost (unplugged, powered off) before the step fails"),
        "reconnect_wait_s": Setting("float", default=10.0, min=0.0, unit="s",
                                    help="how long to keep trying to reopen a lost device"),
    }
    if homing:
        schema["home"] = Setting("str", default="never", choices=HOME_CHOICES,
                                 help="when to find the reference position: never, on_connect "
                                      "(every connect and reconnect) or before_scan")
    return Setting("table", default=REQUIRED if required else None, schema=schema,
                   help="backend filling this role")


HOME_CHOICES = ("never", "on_connect", "before_scan")
#: Longest exposure, settle time or pattern period a profile may ask (ms): 10 minutes. A
#: larger value is a typo (1e12 ms hung the scan for 31 years).
MAX_WAIT_MS = 600_000.0

SCHEMA: dict[str, Setting] = {
    "profile": Setting("table", schema={
        "name": Setting("str", help="short name, used in run directory names"),
        "description": Setting("str", default="", help="one line for humans"),
    }),
    "camera": _device_role(True),
    # a second camera sharing the projector: read by tools that capture both cameras (the
    # simulator's dotshell_sim.two_camera); `dotshell scan` captures [camera] only
    "camera2": _device_role(False),
    "projector": _device_role(True),
    "stage": _device_role(True, homing=True),
    "analyzer": _device_role(False, homing=True),
    "light_source": _device_role(False),
    "coding": _role(True),
    "surface_mesher": _role(False),
    "volume_mesher": _role(False),
    "normalizer": _role(False),
    "calibration": Setting("table", schema={
        "source": Setting("str", default="file", choices=("file", "ground-truth"),
                          help="'file' reads `file`; 'ground-truth' asks a simulated rig"),
        "file": Setting("str", default="", help="calibration.json, relative to the profile"),
    }),
    "calibrate": Setting("table", schema=CALIBRATE_SCHEMA, default={},
                         help="target and poses for `dotshell calibrate` (docs/calibration.md)"),
    "scan": Setting("table", schema={
        "views": Setting("int", default=12, min=1, max=3600,
                         help="views equally spaced over 360 degrees (ignored if angles_deg set)"),
        "angles_deg": Setting("list[float]", default=[], unit="deg",
                              help="explicit stage angles; overrides views"),
        "exposure_ms": Setting("float", default=20.0, min=0.001, max=MAX_WAIT_MS, unit="ms",
                               help="camera exposure (when the camera supports it)"),
        "settle_ms": Setting("float", default=0.0, min=0.0, max=MAX_WAIT_MS, unit="ms",
                             help="wait after each projector change before capturing"),
        "retries": Setting("int", default=2, min=0, max=20,
                           help="re-tries of a frame capture that raised DeviceError (and "
                                "re-captures of a view whose frames fail frame_checks)"),
        "frame_checks": Setting("bool", default=True,
                                help="check each view's frames against what was projected "
                                     "(white above black, pattern + inverse = white + black, "
                                     "frame ids) and capture a failing view again"),
        "acquisition": Setting("str", default="auto", choices=("auto", "sequenced",
                                                                "show-capture"),
                               help="'sequenced': the projector runs the view's patterns as a "
                                    "stored sequence and triggers the camera; 'show-capture': "
                                    "show, settle, capture each frame; 'auto': sequenced when "
                                    "both devices can (docs/hardware.md)"),
        "pattern_period_ms": Setting("float", default=0.0, min=0.0, max=MAX_WAIT_MS, unit="ms",
                                     help="sequenced acquisition: time per pattern; 0 = the "
                                          "shortest both devices allow"),
        "pdi": Setting("bool", default=False,
                       help="polarization difference imaging: capture every pattern with the "
                            "analyzer parallel and perpendicular, reconstruct from |I∥ − I⊥|"),
        "pdi_angles_deg": Setting("list[float]", default=[0.0, 90.0], length=2, unit="deg",
                                  help="analyzer angles (parallel, perpendicular) relative to "
                                       "the polarizer"),
    }, default={}),
    "processing": Setting("table", schema={
        "roi": Setting("table", schema={
            "radius_mm": Setting("float", default=50.0, min=0.001, unit="mm",
                                 help="keep points within this distance of the turntable axis"),
            "z_min_mm": Setting("float", default=0.5, unit="mm",
                                help="drop points below this height above the stage plate"),
            "z_max_mm": Setting("float", default=200.0, unit="mm", help="drop points above"),
        }, default={}),
        "row_tolerance_px": Setting("float", default=1.5, min=0.1, unit="px",
                                    help="max reprojection error of a point from the "
                                         "decoded column and row (column+row codings)"),
        "max_depth_jump_mm": Setting("float", default=0.5, min=0.0, unit="mm",
                                     help="speckle filter: drop points whose depth differs from "
                                          "the median of their 5x5 camera neighbourhood by more "
                                          "(0 = off)"),
        "min_ray_angle_deg": Setting("float", default=5.0, min=0.0, max=89.0, unit="deg",
                                     help="drop points whose camera ray meets the projector "
                                          "ray (columns only: the column plane) at less"),
    }, default={}),
    "validation": Setting("table", schema={
        "shape": Setting("str", default="none", choices=("none", "cylinder"),
                         help="known shape of the sample, for the accuracy report"),
        "radius_mm": Setting("float", default=0.0, min=0.0, unit="mm", help="true radius"),
        "height_mm": Setting("float", default=0.0, min=0.0, unit="mm", help="true height"),
        "edge_margin_mm": Setting("float", default=1.0, min=0.0, unit="mm",
                                  help="band excluded at the top and bottom edges"),
        "cell_deg": Setting("float", default=2.0, min=0.1, unit="deg",
                            help="coverage cell width around the axis"),
        "cell_mm": Setting("float", default=1.0, min=0.05, unit="mm", help="coverage cell height"),
    }, default={}),
    "mesh": Setting("table", schema=MESH_SCHEMA, default={},
                    help="surface and volume meshing of the cloud (docs/meshing.md)"),
    "transillumination": Setting("table", schema=TRANSILLUMINATION_SCHEMA, default={},
                                 help="trans-illumination capture (docs/transillumination.md)"),
    "normalize": Setting("table", schema=NORMALIZE_SCHEMA, default={},
                         help="intensity normalization on the surface "
                              "(docs/transillumination.md)"),
    "export": Setting("table", default={}, help="one sub-table per exporter backend to run "
                      "after processing, holding that exporter's settings: [export.NAME]"),
    "outputs": Setting("table", schema={
        "previews": Setting("bool", default=True, help="render PNG previews into the run"),
        "preview_view": Setting("int", default=0, min=0, help="view shown in frame previews"),
    }, default={}),
}


@dataclass(frozen=True)
class Profile:
    """A validated profile: its core sections as typed objects (:mod:`.sections`), its
    backend roles and exports as the plugins' own settings.

    Attributes:
        source: the file it came from (or ``"<dict>"``), named in errors.
        base_dir: directory relative paths in the profile are resolved against.
        info, scan, processing, validation, outputs, mesh, transillumination, normalize,
        calibration, calibrate: the sections of the same name (``[profile]`` is ``info``).
    """

    source: str
    base_dir: Path
    info: ProfileInfo
    scan: ScanSettings
    processing: ProcessingSettings
    validation: ValidationSettings
    outputs: OutputsSettings
    mesh: MeshSettings
    transillumination: TransilluminationSettings
    normalize: NormalizeSettings
    calibration: CalibrationSource
    calibrate: CalibrateSettings
    _data: dict[str, Any] = field(repr=False)

    @classmethod
    def from_validated(cls, data: dict[str, Any], source: str, base_dir: Path) -> Profile:
        """The profile of a dict :func:`validate_settings` filled in against :data:`SCHEMA`."""
        return cls(source=source, base_dir=base_dir, _data=data,
                   info=ProfileInfo.from_table(data["profile"]),
                   scan=ScanSettings.from_table(data["scan"]),
                   processing=ProcessingSettings.from_table(data["processing"]),
                   validation=ValidationSettings.from_table(data["validation"]),
                   outputs=OutputsSettings.from_table(data["outputs"]),
                   mesh=MeshSettings.from_table(data["mesh"]),
                   transillumination=TransilluminationSettings.from_table(
                       data["transillumination"]),
                   normalize=NormalizeSettings.from_table(data["normalize"]),
                   calibration=CalibrationSource.from_table(data["calibration"]),
                   calibrate=CalibrateSettings.from_table(data["calibrate"]))

    @property
    def data(self) -> dict[str, Any]:
        """The raw validated TOML (defaults filled in, backend settings included), for
        third-party plugins; a copy, so changing it changes nothing. Core code reads the
        typed sections instead."""
        return copy.deepcopy(self._data)

    @property
    def name(self) -> str:
        return self.info.name

    @property
    def export(self) -> dict[str, dict[str, Any]]:
        """``[export.NAME]`` tables: exporter backend name → its validated settings."""
        return self._data["export"]

    def role(self, role: str) -> dict[str, Any] | None:
        """``{"backend": ..., "settings": {...}}`` for a role, or None when not configured."""
        return self._data.get(role)

    def required_role(self, role: str) -> dict[str, Any]:
        """:meth:`role` for a role the profile must configure (camera, projector, stage,
        coding) or one the caller checked; a ProfileError naming the missing table otherwise."""
        section = self.data.get(role)
        if section is None:
            raise ProfileError(f"{self.source}: no [{role}] table; add one naming its backend.")
        return section

    def angles_deg(self) -> list[float]:
        """Stage angles of the scan's views in degrees."""
        return self.scan.view_angles_deg()

    def calibration_path(self) -> Path | None:
        if self.calibration.source != "file":
            return None
        return (self.base_dir / self.calibration.file).resolve()

    def raw(self) -> dict[str, Any]:
        """The profile as a plain dict, writable back to TOML. TOML has no null: keys whose
        value is None (absent roles, "automatic" settings) are left out, which reads back as
        the same defaults."""
        return _drop_none(self._data)


def _drop_none(d: dict[str, Any]) -> dict[str, Any]:
    return {k: _drop_none(v) if isinstance(v, dict) else copy.deepcopy(v)
            for k, v in d.items() if v is not None}


def apply_overrides(data: dict[str, Any], overrides: list[str], where: str) -> dict[str, Any]:
    """Apply ``key.path=VALUE`` overrides (VALUE in TOML syntax; bare words are strings)."""
    data = copy.deepcopy(data)
    for item in overrides:
        if "=" not in item:
            raise ProfileError(f"override {item!r} is not KEY=VALUE, e.g. scan.views=24.")
        key, text = item.split("=", 1)
        try:
            value = tomllib.loads(f"v = {text}")["v"]
        except tomllib.TOMLDecodeError:
            value = text
        node = data
        parts = key.strip().split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ProfileError(f"{where}: override {item!r}: [{part}] is not a table.")
        node[parts[-1]] = value
    return data


def validate_profile(raw: dict[str, Any], pm: PluginManager, where: str,
                     base_dir: Path | str = ".") -> Profile:
    """Validate a parsed profile dict; see :func:`load_profile`."""
    data = validate_settings(SCHEMA, raw, where)
    for role in (*DEVICE_ROLES, "camera2", "coding", "surface_mesher", "volume_mesher",
                 "normalizer"):
        section = data.get(role)
        if section is None:
            continue
        info = pm.backend(role.removesuffix("2"), section["backend"], where)
        section["settings"] = validate_settings(
            info.backend.settings_schema, section["settings"], where, f"{role}.settings")
    for name, settings in data["export"].items():
        if not isinstance(settings, dict):
            raise ProfileError(f"{where}: [export.{name}] must be a table of that exporter's "
                               f"settings (it is {settings!r}); write [export.{name}] on its own line.")
        info = pm.backend("exporter", name, where)
        data["export"][name] = validate_settings(info.backend.settings_schema, settings, where,
                                                 f"export.{name}")
    cal = data["calibration"]
    if cal["source"] == "file" and not cal["file"]:
        raise ProfileError(f"{where}: [calibration] needs file = \"calibration.json\" (a "
                           "calibration written by dotshell), or source = \"ground-truth\" on a "
                           "simulated rig.")
    _check_transillumination(data, where)
    _check_roi(data["processing"]["roi"], where)
    return Profile.from_validated(data, where, Path(base_dir))


def _check_roi(roi: dict[str, Any], where: str) -> None:
    if roi["z_min_mm"] >= roi["z_max_mm"]:
        raise ProfileError(f"{where}: [processing.roi] z_min_mm = {roi['z_min_mm']:g} is not below "
                           f"z_max_mm = {roi['z_max_mm']:g}: no point could be kept; give a "
                           "height band with z_min_mm < z_max_mm.")


def _check_transillumination(data: dict[str, Any], where: str) -> None:
    t = data["transillumination"]
    for i, target in enumerate(t["targets_mm"]):
        if len(target) != 2:
            raise ProfileError(f"{where}: [transillumination] targets_mm[{i}] = {target!r} is not "
                               "a [lateral, height] pair of numbers in mm, e.g. [0.0, 10.0].")
    if t["enabled"] and data.get("light_source") is None:
        raise ProfileError(f"{where}: [transillumination] enabled = true needs a [light_source] "
                           "(the trans-illumination laser), e.g. backend = \"sim-laser\".")
    n_views = len(data["scan"]["angles_deg"]) or data["scan"]["views"]
    bad = [v for v in t["views"] if not 0 <= v < n_views]
    if bad and t["enabled"]:
        raise ProfileError(f"{where}: [transillumination] views {bad} are not views of this "
                           f"scan (0 .. {n_views - 1}).")


def load_profile(path: str | Path, pm: PluginManager, overrides: list[str] | None = None) -> Profile:
    """Read, override and validate a profile file; a bare name that is not a file
    (``sim-metal-cylinder``) is the shipped profile of that name (:mod:`dotshell.shipped`).

    Raises:
        ProfileError: missing/unreadable file, TOML syntax error or invalid content.
        PluginError: a backend name no installed plugin provides.
    """
    from dotshell.shipped import resolve, unknown_hint

    path = resolve("profiles", path)
    if path.is_dir():
        inside = sorted(p.name for p in path.glob("*.toml") if p.is_file())
        raise ProfileError(f"profile {path} is a directory; give a profile TOML file in it, "
                           f"e.g. one of {inside or 'none'}.")
    if path.exists() and not path.is_file():
        raise ProfileError(f"profile {path} is not a regular file (a FIFO, device or socket); "
                           "give a profile TOML file.")
    if not path.is_file():
        near = sorted(p.name for p in path.parent.glob("*.toml") if p.is_file()) \
            if path.parent.is_dir() else []
        hint = f" Profiles in {path.parent}: {', '.join(near)}." if near else ""
        raise ProfileError(f"profile {path} does not exist.{hint} {unknown_hint('profiles')}")
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ProfileError(f"{path}: not valid TOML ({exc}). Fix the syntax at that line.") from None
    except RecursionError:
        raise ProfileError(f"{path}: not a profile: its arrays or tables are nested too deeply "
                           "to read. Fix or replace the file.") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ProfileError(f"{path}: cannot be read ({exc}).") from None
    if overrides:
        raw = apply_overrides(raw, overrides, str(path))
    return validate_profile(raw, pm, str(path), path.parent)
