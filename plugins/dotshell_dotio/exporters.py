"""The exporters of :mod:`dotshell_dotio`, each built on first use (``python_name`` targets of
this package's ``dotshell.toml``): a backend imports only its own writer's module."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from dotshell.backends import Backend
from dotshell.fem.meshfiles import read_optodes, read_volume
from dotshell.settings import Setting


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
        from dotshell_dotio.common import write_common

        run_dir = Path(run_dir)
        return write_common(run_dir, run_dir / (self.settings["dir"] or "meshio"),
                            self.settings["formats"])


def nirfast() -> Backend:
    from dotshell_dotio.nirfast import write_nirfast

    return Backend("nirfast", lambda settings, context=None: _MeshExporter(
        "nirfast", write_nirfast, settings), dict(_FILES))


def toast() -> Backend:
    from dotshell_dotio.toast import write_toast

    return Backend("toast", lambda settings, context=None: _MeshExporter(
        "toast", write_toast, settings), dict(_FILES))


def meshio() -> Backend:
    from dotshell_dotio.common import FORMATS

    common = {
        "dir": _FILES["dir"],
        "formats": Setting("list[str]", ["vtu", "gmsh", "stl", "ply"], "formats to write: "
                           + ", ".join(FORMATS), choices=None),
    }
    return Backend("meshio", lambda settings, context=None: _check_formats(settings), common)


def _check_formats(settings: dict[str, Any]) -> _CommonExporter:
    from dotshell.errors import ProfileError
    from dotshell_dotio.common import FORMATS

    bad = [f for f in settings["formats"] if f not in FORMATS]
    if bad:
        raise ProfileError(f"[export.meshio] formats: {bad[0]!r} is not a supported format. "
                           f"Valid choices: {', '.join(FORMATS)}.")
    return _CommonExporter(settings)
