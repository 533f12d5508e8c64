"""What a plugin hands the core for each backend it provides."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

from dotshell.settings import Setting

#: Roles a backend can fill, and the hook that provides them.
ROLES: dict[str, str] = {
    "camera": "dotshell_cameras",
    "projector": "dotshell_projectors",
    "stage": "dotshell_stages",
    "analyzer": "dotshell_analyzers",
    "light_source": "dotshell_light_sources",
    "coding": "dotshell_codings",
    "surface_mesher": "dotshell_surface_meshers",
    "volume_mesher": "dotshell_volume_meshers",
    "normalizer": "dotshell_normalizers",
    "exporter": "dotshell_exporters",
}


@dataclass
class RigContext:
    """Passed to every device factory of one rig.

    Attributes:
        shared: scratch space shared by the devices of this rig (e.g. one serial bus serving a
            stage and an analyzer, or the simulator's world). Key it by your plugin name.
        base_dir: directory of the profile, for resolving relative paths in settings.
    """

    shared: dict[str, Any] = field(default_factory=dict)
    base_dir: str = "."


@dataclass(frozen=True)
class Backend:
    """One backend for one role.

    Attributes:
        name: the name profiles use (``backend = "NAME"``), unique per role; lower-case-dashes.
        factory: ``factory(settings: dict, context: RigContext) -> object`` returning an object
            satisfying the role's protocol (see :mod:`dotshell.devices`, :mod:`dotshell.coding`).
            ``settings`` has been validated against ``settings_schema`` with defaults filled in.
        settings_schema: the keys of the profile's ``[ROLE.settings]`` table.
        summary: one line for ``dotshell plugins``.
    """

    name: str
    factory: Callable[..., Any]
    settings_schema: Mapping[str, Setting] = field(default_factory=dict)
    summary: str = ""
