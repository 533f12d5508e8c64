"""The meshers' backends, each built on first use (``python_name`` targets of this package's
``dotshell.toml``): importing this module imports no mesher (nor open3d, tetgen)."""

from __future__ import annotations

from typing import Any

from dotshell.backends import Backend


def open3d_poisson() -> Backend:
    from dotshell_meshing.surface import SETTINGS, PoissonSurfaceMesher

    def make(settings: dict[str, Any], context: Any = None) -> PoissonSurfaceMesher:
        return PoissonSurfaceMesher(settings)

    return Backend("open3d-poisson", make, SETTINGS)


def tetgen() -> Backend:
    from dotshell_meshing.volume import SETTINGS, TetgenVolumeMesher

    def make(settings: dict[str, Any], context: Any = None) -> TetgenVolumeMesher:
        return TetgenVolumeMesher(settings)

    return Backend("tetgen", make, SETTINGS)
