"""NIRFAST "standard" (stnd) mesh files: writer and reader. Format: ``docs/formats.md``.

``NAME.node``   one row per node, tab-separated: boundary flag (1 on the surface, 0 inside),
                x, y, z (mm)
``NAME.elem``   one row per tetrahedron, tab-separated 1-based node numbers (positively
                oriented here; NIRFAST sorts them on load)
``NAME.param``  header line ``stnd``, then per node: μa (1/mm), κ = 1/(3(μa + μs')) (mm), n
``NAME.region`` per node region label (1, 2, ...)
``NAME.source`` header ``num x y z fwhm``, one point source per row (fwhm 0) — with optodes
``NAME.meas``   header ``num x y z``, one detector per row — with optodes
``NAME.link``   header ``source detector active``, 1-based pairs, active = 1 — with optodes
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dotshell.errors import RunError
from dotshell.fem.meshes import TetMesh
from dotshell.fem.meshfiles import Optodes
from dotshell.run.store import atomic_write_text

from dotshell_dotio.optics import kappa_mm, node_optics

__all__ = ["NirfastMesh", "kappa_mm", "read_nirfast", "write_nirfast"]


def _rows(array: np.ndarray, fmt: str, sep: str) -> str:
    return "".join(sep.join(fmt % v for v in row) + "\n" for row in np.atleast_2d(array))


def write_nirfast(directory: Path, stem: str, mesh: TetMesh, optodes: Optodes) -> list[Path]:
    """Write ``stem.node/.elem/.param/.region`` (+ ``.source/.meas/.link`` with optodes)."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    optics = node_optics(mesh)
    files = {
        "node": _rows(np.column_stack([mesh.boundary_nodes.astype(int), mesh.nodes]),
                      "%.10g", "\t"),
        "elem": _rows(mesh.tets + 1, "%d", "\t"),
        "param": "stnd\n" + _rows(np.column_stack(
            [optics.mua_per_mm, optics.kappa_mm, optics.refractive_index]), "%.10g", " "),
        "region": _rows(np.asarray(optics.region, float)[:, None], "%d", "\t"),
    }
    if len(optodes.sources_mm):
        num = np.arange(1, len(optodes.sources_mm) + 1)
        files["source"] = "num x y z fwhm\n" + _rows(
            np.column_stack([num, optodes.sources_mm, np.zeros(len(num))]), "%.10g", " ")
    if len(optodes.detectors_mm):
        num = np.arange(1, len(optodes.detectors_mm) + 1)
        files["meas"] = "num x y z\n" + _rows(np.column_stack([num, optodes.detectors_mm]),
                                              "%.10g", " ")
    if len(optodes.links):
        files["link"] = "source detector active\n" + _rows(
            np.column_stack([optodes.links + 1, np.ones(len(optodes.links), int)]), "%d", " ")
    out = []
    for ext, text in files.items():
        p = d / f"{stem}.{ext}"
        atomic_write_text(p, text)
        out.append(p)
    return out


@dataclass
class NirfastMesh:
    """What :func:`read_nirfast` found (0-based elements, links; arrays in file order)."""

    bndvtx: np.ndarray
    nodes: np.ndarray
    elements: np.ndarray
    mua: np.ndarray
    kappa: np.ndarray
    ri: np.ndarray
    region: np.ndarray
    sources: np.ndarray | None = None
    detectors: np.ndarray | None = None
    links: np.ndarray | None = None


def _table(path: Path, header: str | None) -> np.ndarray:
    if not path.is_file():
        raise RunError(f"NIRFAST file {path} is missing.")
    lines = path.read_text().splitlines()
    if header is not None:
        if not lines or lines[0].split() != header.split():
            raise RunError(f"{path}: first line must be {header!r}, found "
                           f"{lines[0] if lines else ''!r}.")
        lines = lines[1:]
    return np.array([[float(x) for x in ln.split()] for ln in lines if ln.strip()])


def read_nirfast(directory: Path, stem: str) -> NirfastMesh:
    """Read a NIRFAST stnd mesh written by :func:`write_nirfast` (or by NIRFAST)."""
    d = Path(directory)
    node = _table(d / f"{stem}.node", None)
    param = _table(d / f"{stem}.param", "stnd")
    out = NirfastMesh(
        bndvtx=node[:, 0].astype(int), nodes=node[:, 1:4],
        elements=_table(d / f"{stem}.elem", None).astype(np.int64) - 1,
        mua=param[:, 0], kappa=param[:, 1], ri=param[:, 2],
        region=_table(d / f"{stem}.region", None)[:, 0].astype(int))
    if (d / f"{stem}.source").is_file():
        out.sources = _table(d / f"{stem}.source", "num x y z fwhm")[:, 1:4]
    if (d / f"{stem}.meas").is_file():
        out.detectors = _table(d / f"{stem}.meas", "num x y z")[:, 1:4]
    if (d / f"{stem}.link").is_file():
        link = _table(d / f"{stem}.link", "source detector active").astype(np.int64)
        out.links = link[link[:, 2] == 1, :2] - 1
    return out
