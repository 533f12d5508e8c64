"""dotshell_dotio — exporters of a run's meshes for diffuse optical tomography software:
NIRFAST standard meshes, TOAST++ meshes and QM files, and common formats through meshio.

Registered under the ``dotshell`` entry-point group as ``dotio = "dotshell_dotio"``. Every
exporter reads the mesh directory it is given (a run directory, or ``meshes/<d>mm/`` in it):
``volume.vtu`` (nodes, positively oriented tetrahedra, per-node optical properties),
``surface.ply`` and ``optodes.json``; formats in ``docs/formats.md``.

The exporters are declared in ``dotshell.toml`` and built in :mod:`dotshell_dotio.exporters`:
this module imports no writer.
"""

from __future__ import annotations

from dotshell import hookimpl
from dotshell.backends import Backend
from dotshell.manifest import backends_of


@hookimpl
def dotshell_exporters() -> list[Backend]:
    """All exporters (when this package is registered as a plain pluggy plugin)."""
    return backends_of(__name__, "exporter")
