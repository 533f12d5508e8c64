"""The camera backends, each built on first use (``python_name`` targets of this package's
``dotshell.toml``): importing this module imports no driver (nor cv2, harvesters, pylablib)."""

from __future__ import annotations

from typing import Any

from dotshell.backends import Backend, RigContext


def _base(context: RigContext | None) -> str:
    return context.base_dir if context is not None else "."


def opencv() -> Backend:
    from dotshell_cameras.opencv import SETTINGS_SCHEMA, OpenCVCamera

    def make(settings: dict[str, Any], context: RigContext | None = None) -> OpenCVCamera:
        return OpenCVCamera(settings, _base(context))

    return Backend("opencv", make, SETTINGS_SCHEMA)


def genicam() -> Backend:
    from dotshell_cameras.genicam import SETTINGS_SCHEMA, GenICamCamera

    def make(settings: dict[str, Any], context: RigContext | None = None) -> GenICamCamera:
        return GenICamCamera(settings, _base(context))

    return Backend("genicam", make, SETTINGS_SCHEMA)


def scientific() -> Backend:
    from dotshell_cameras.scientific import SETTINGS_SCHEMA, ScientificCamera

    def make(settings: dict[str, Any], context: RigContext | None = None) -> ScientificCamera:
        return ScientificCamera(settings)

    return Backend("scientific", make, SETTINGS_SCHEMA)
