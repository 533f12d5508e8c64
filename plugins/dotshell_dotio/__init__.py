"""dotshell_dotio — exporters of a run's meshes for diffuse optical tomography software:
NIRFAST standard meshes, TOAST++ meshes and QM files, and common formats through meshio.

Registered under the ``dotshell`` entry-point group as ``dotio = "dotshell_dotio"``. Every
exporter reads the mesh directory it is given (a run directory, or ``meshes/<d>mm/`` in it):
``volume.vtu`` (nodes, positively oriented tetrahedra, per-node optical properties),
``surface.ply`` and ``optodes.json``; formats in ``docs/formats.md``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from dotshell import hookimpl
from dotshell.backends import Backend
from dotshell.fem.meshfiles import read_optodes, read_volume
from dotshell.settings import Setting

from dotshell_dotio.common import FORMATS, write_common
from dotshell_dotio.nirfast import write_nirfast
from dotshell_dotio.toast import write_toast

_FILES = {
    "dir": Setting("str", "", "sub-directory of the run the files go to (default: the "
                   "exporter's name)"),
    "stem": Setting("str", "mesh", "file name without extension"),
}


class _MeshExporter:
    def __init__(self, name: str, writer, settings: dict[str, Any]):
        self.name = name
        self.writer = writer
        self.settings = settings

    def export(self, run_dir: Path) -> list[Path]:
        run_dir = Path(run_dir)
        mesh = read_volume(run_dir / "volume.vtu")
        optodes = read_optodes(run_dir / "optodes.json")
        return self.writer(run_dir / (self.settings["dir"] or self.name), self.settings["stem"],
                           mesh, optodes)


class _CommonExporter:
    def __init__(self, settings: dict[str, Any]):
        self.settings = settings

    def export(self, run_dir: Path) -> list[Path]:
        run_dir = Path(run_dir)
        return write_common(run_dir, run_dir / (self.settings["dir"] or "meshio"),
                            self.settings["formats"])


@hookimpl
def dotshell_exporters() -> list[Backend]:
    common = {
        "dir": _FILES["dir"],
        "formats": Setting("list[str]", ["vtu", "gmsh", "stl", "ply"], "formats to write: "
                           + ", ".join(FORMATS), choices=None),
    }
    return [
        Backend("nirfast", lambda settings, context=None: _MeshExporter(
            "nirfast", write_nirfast, settings), dict(_FILES),
            "NIRFAST standard mesh: .node .elem .param .region (+ .source .meas .link)"),
        Backend("toast", lambda settings, context=None: _MeshExporter(
            "toast", write_toast, settings), dict(_FILES),
            "TOAST++ mesh (MeshData 5.0 .msh) and .qm source/detector file"),
        Backend("meshio", lambda settings, context=None: _check_formats(settings), common,
                "volume/surface meshes in common formats through meshio (VTU, Gmsh, STL, ...)"),
    ]


def _check_formats(settings: dict[str, Any]) -> _CommonExporter:
    from dotshell.errors import ProfileError

    bad = [f for f in settings["formats"] if f not in FORMATS]
    if bad:
        raise ProfileError(f"[export.meshio] formats: {bad[0]!r} is not a supported format. "
                           f"Valid choices: {', '.join(FORMATS)}.")
    return _CommonExporter(settings)
