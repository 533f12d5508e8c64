"""The example plugin's exporter: ``cloud.xyz`` (one ``x y z`` line per point, millimetres)
from a run's ``cloud.ply``."""

from __future__ import annotations

from pathlib import Path

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


#: the backend ``dotshell.toml`` names (python_name = "dotshell_xyz_export.exporter:XYZ_TEXT");
#: its summary is the manifest's
XYZ_TEXT = Backend(
    name="xyz-text",
    factory=lambda settings, context: XyzExporter(settings["delimiter"], settings["decimals"]),
    settings_schema={
        "delimiter": Setting("str", default=" ", help="separator between x, y and z"),
        "decimals": Setting("int", default=4, min=0, max=9, help="digits after the point (mm)"),
    },
)
