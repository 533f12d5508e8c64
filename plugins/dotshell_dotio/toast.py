"""TOAST++ mesh (``.msh``, MeshData 5.0) and source/detector (``.qm``) files: writer and
reader. Format: ``docs/formats.md``.

``NAME.msh``::

    MeshData 5.0

    NodeList <N> 1
    B[x y z]R<r>        boundary node (N[...] for an internal node), region r (0-based)
    ...

    ElementList <M>
    c n1 n2 n3 n4       4-noded tetrahedron, 1-based, positively oriented
    ...

    [ParameterList]N
    Size <N>
    Param1 MUA
    Param2 KAPPA
    Param3 N
    Data
    mua kappa n         per node (1/mm, mm, -)

``NAME.qm``: ``QM file 3D``, ``Dimension 3``, ``SourceList``, ``MeasurementList`` and a
``LinkList`` with one line ``count: d0 d1 ...`` (0-based detectors) per source.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dotshell.errors import RunError
from dotshell.fem.meshes import TetMesh
from dotshell.fem.meshfiles import Optodes
from dotshell.run.store import atomic_write_text

from dotshell_dotio.optics import node_optics


def msh_text(mesh: TetMesh) -> str:
    n = len(mesh.nodes)
    optics = node_optics(mesh)
    region = np.asarray(optics.region, int) - 1
    flag = np.where(mesh.boundary_nodes, "B", "N")
    lines = ["MeshData 5.0", "", f"NodeList {n} 1"]
    lines += [f"{f}[{x:.10g} {y:.10g} {z:.10g}]R{r}"
              for f, (x, y, z), r in zip(flag, mesh.nodes, region)]
    lines += ["", f"ElementList {len(mesh.tets)}"]
    lines += ["c " + " ".join(str(int(i)) for i in t) for t in mesh.tets + 1]
    lines += ["", "[ParameterList]N", f"Size {n}", "Param1 MUA", "Param2 KAPPA", "Param3 N",
              "Data"]
    lines += [f"{a:.10g} {k:.10g} {r:.10g}" for a, k, r in zip(
        optics.mua_per_mm, optics.kappa_mm, optics.refractive_index)]
    return "\n".join(lines) + "\n"


def qm_text(optodes: Optodes) -> str:
    lines = ["QM file 3D", "Dimension 3", "", f"SourceList {len(optodes.sources_mm)}"]
    lines += [" ".join(f"{v:.10g}" for v in p) for p in optodes.sources_mm]
    lines += ["", f"MeasurementList {len(optodes.detectors_mm)}"]
    lines += [" ".join(f"{v:.10g}" for v in p) for p in optodes.detectors_mm]
    lines += ["", "LinkList"]
    for s in range(len(optodes.sources_mm)):
        dets = optodes.links[optodes.links[:, 0] == s, 1]
        lines.append(f"{len(dets)}: " + " ".join(str(int(d)) for d in dets))
    return "\n".join(lines) + "\n"


def write_toast(directory: Path, stem: str, mesh: TetMesh, optodes: Optodes) -> list[Path]:
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    out = [d / f"{stem}.msh"]
    atomic_write_text(out[0], msh_text(mesh))
    if not optodes.empty:
        out.append(d / f"{stem}.qm")
        atomic_write_text(out[1], qm_text(optodes))
    return out


@dataclass
class ToastMesh:
    """What :func:`read_msh` found (0-based elements)."""

    nodes: np.ndarray
    boundary: np.ndarray
    region: np.ndarray
    element_types: list[str]
    elements: np.ndarray
    params: dict[str, np.ndarray]


_NODE = re.compile(r"^([A-Za-z])\[([^\]]*)\](?:R(-?\d+))?")


def _fail(path: Path, what: str) -> RunError:
    return RunError(f"{path}: not a TOAST MeshData 5.0 file ({what}).")


def read_msh(path: Path) -> ToastMesh:
    path = Path(path)
    if not path.is_file():
        raise RunError(f"TOAST mesh {path} is missing.")
    lines = [ln.strip() for ln in path.read_text().splitlines()]
    it = iter(ln for ln in lines if ln)
    if next(it, "") != "MeshData 5.0":
        raise _fail(path, "first line is not 'MeshData 5.0'")
    head = next(it, "").split()
    if head[:1] != ["NodeList"]:
        raise _fail(path, "no NodeList")
    nodes, flags, regions = [], [], []
    for _ in range(int(head[1])):
        m = _NODE.match(next(it, ""))
        if not m:
            raise _fail(path, "bad node line")
        flags.append(m.group(1))
        nodes.append([float(x) for x in m.group(2).split()])
        regions.append(int(m.group(3) or 0))
    head = next(it, "").split()
    if head[:1] != ["ElementList"]:
        raise _fail(path, "no ElementList")
    types, elems = [], []
    for _ in range(int(head[1])):
        parts = next(it, "").split()
        types.append(parts[0])
        elems.append([int(x) for x in parts[1:5]])
    params: dict[str, np.ndarray] = {}
    rest = list(it)
    if rest and rest[0].startswith("[ParameterList]"):
        size = int(rest[1].split()[1])
        names = [ln.split()[1] for ln in rest[2:] if ln.startswith("Param")]
        start = rest.index("Data") + 1
        data = np.array([[float(x) for x in ln.split()] for ln in rest[start:start + size]])
        params = {name: data[:, i] for i, name in enumerate(names)}
    return ToastMesh(np.array(nodes), np.array(flags) == "B", np.array(regions), types,
                     np.array(elems, np.int64) - 1, params)


def read_qm(path: Path) -> Optodes:
    path = Path(path)
    lines = [ln.strip() for ln in path.read_text().splitlines() if ln.strip()]
    if lines[:2] != ["QM file 3D", "Dimension 3"]:
        raise RunError(f"{path}: not a TOAST 3-D QM file.")
    ns = int(lines[2].split()[1])
    src = [[float(x) for x in ln.split()] for ln in lines[3:3 + ns]]
    k = 3 + ns
    nd = int(lines[k].split()[1])
    det = [[float(x) for x in ln.split()] for ln in lines[k + 1:k + 1 + nd]]
    k += 1 + nd
    if lines[k] != "LinkList":
        raise RunError(f"{path}: no LinkList.")
    links = []
    for s, ln in enumerate(lines[k + 1:k + 1 + ns]):
        count, _, rest = ln.partition(":")
        dets = [int(x) for x in rest.split()]
        if len(dets) != int(count):
            raise RunError(f"{path}: source {s} lists {len(dets)} detectors, says {count}.")
        links += [[s, d] for d in dets]
    return Optodes(src, det, links)
