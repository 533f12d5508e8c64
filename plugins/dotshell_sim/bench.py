"""Helpers around the simulated bench: scale it down for fast tests, build a rig from a profile.

:func:`scale_profile` keeps the geometry (poses, field of view, scene) and changes only the
pixel grids of the sim camera and sim projector, with :meth:`dotshell.geometry.lens.Lens.scaled`
semantics (focal lengths × factor, principal points ``(c + 0.5)·factor − 0.5``, sizes rounded),
and the defocus sigmas (pixels) × factor so the optical blur stays the same in millimetres.
"""

from __future__ import annotations

import copy
from typing import Any

from dotshell.backends import RigContext

from dotshell_sim.devices import (
    CAMERA_SCHEMA, PROJECTOR_SCHEMA, make_analyzer, make_camera, make_laser, make_projector,
    make_turntable)

_SCHEMAS = {"sim-camera": CAMERA_SCHEMA, "sim-projector": PROJECTOR_SCHEMA}
_FACTORIES = {"sim-camera": make_camera, "sim-projector": make_projector,
              "sim-turntable": make_turntable, "sim-analyzer": make_analyzer,
              "sim-laser": make_laser}


def scale_settings(settings: dict[str, Any], backend: str, factor: float) -> dict[str, Any]:
    """Settings of a ``sim-camera`` / ``sim-projector`` at ``factor`` times the resolution."""
    if factor <= 0:
        raise ValueError(f"scale factor must be positive, got {factor}")
    schema = _SCHEMAS[backend]
    out = dict(settings)

    def get(key):
        v = settings.get(key)
        return schema[key].default if v is None else v

    width, height = get("width"), get("height")
    out["width"] = round(width * factor)
    out["height"] = round(height * factor)
    out["focal_px"] = float(get("focal_px")) * factor
    for key in ("cx", "cy"):
        if settings.get(key) is not None:
            out[key] = (float(settings[key]) + 0.5) * factor - 0.5
    out["defocus_sigma_px"] = float(get("defocus_sigma_px")) * factor
    return out


def scale_profile(profile: dict[str, Any], factor: float) -> dict[str, Any]:
    """A deep copy of a parsed profile with its sim cameras (``[camera]``, ``[camera2]``) and
    projector scaled by ``factor`` (e.g. 0.25 → 320×256 camera, 256×192 projector for the
    reference bench). Sections using other backends are left unchanged."""
    out = copy.deepcopy(profile)
    for role in ("camera", "camera2", "projector"):
        section = out.get(role)
        if isinstance(section, dict) and section.get("backend") in _SCHEMAS:
            section["settings"] = scale_settings(section.get("settings") or {},
                                                 section["backend"], factor)
    return out


def build_rig(profile: dict[str, Any], context: RigContext | None = None) -> dict[str, Any]:
    """Sim devices for every device role of ``profile`` whose backend is a sim backend, sharing
    one world (a convenience for tests and scripts; the core has its own loader). Returns
    ``{role: device}``; devices are not connected."""
    context = context or RigContext()
    rig = {}
    for role in ("camera", "projector", "stage", "analyzer", "light_source"):
        section = profile.get(role)
        if isinstance(section, dict) and section.get("backend") in _FACTORIES:
            rig[role] = _FACTORIES[section["backend"]](settings=section.get("settings") or {},
                                                       context=context)
    return rig
