"""Example third-party plugin: an exporter writing ``cloud.xyz`` (one ``x y z`` line per point,
millimetres) from a run's ``cloud.ply``. Enable it in a profile with::

    [export.xyz-text]
    delimiter = ","
    decimals = 4
"""

from __future__ import annotations

from pathlib import Path

from dotshell import hookimpl
from dotshell.backends import Backend
from dotshell.run.ply import read_ply
from dotshell.settings import Setting
from dotshell.run.store import atomic_write_text


class XyzExporter:
    def __init__(self, delimiter: str, decimals: int) -> None:
        self.delimiter = delimiter
        self.decimals = decimals

    def export(self, run_dir: Path) -> list[Path]:
        points, _ = read_ply(Path(run_dir) / "cloud.ply")
        lines = [self.delimiter.join(f"{v:.{self.decimals}f}" for v in p) for p in points]
        out = Path(run_dir) / "cloud.xyz"
        atomic_write_text(out, "\n".join(lines) + "\n")
        return [out]


@hookimpl
def dotshell_exporters():
    return [Backend(
        name="xyz-text",
        factory=lambda settings, context: XyzExporter(settings["delimiter"], settings["decimals"]),
        settings_schema={
            "delimiter": Setting("str", default=" ", help="separator between x, y and z"),
            "decimals": Setting("int", default=4, min=0, max=9, help="digits after the point (mm)"),
        },
        summary="merged cloud as plain-text XYZ (mm)",
    )]
