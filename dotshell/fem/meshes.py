"""FEM meshes: the surface and tetrahedral mesh types the meshers exchange, and their geometry
and quality measures (numpy; lengths in mm, volumes in mm³, angles in degrees), and the
sparsity pattern linear-element matrices on them share. The loops over elements (boundary
faces, the pattern) are compiled, in :mod:`dotshell.fem.kernels`.

Conventions:

* :class:`TriangleSurface` — triangles ordered counter-clockwise seen from outside, so the
  right-hand normals point out of the enclosed solid.
* :class:`TetMesh` — 0-based node indices; every tetrahedron ``(a, b, c, d)`` is *positively
  oriented*: ``det[b − a, c − a, d − a] > 0`` (``d`` lies on the side the right-hand normal
  of ``(a, b, c)`` points to). NIRFAST and TOAST both accept this order.

Roles (see :mod:`dotshell.hookspecs`): a *surface mesher* factory returns an object with
``surface(points_mm, viewpoints_mm, node_distance_mm, bottom_z_mm) -> SurfaceResult``; a
*volume mesher* factory returns an object with ``volume(surface, node_distance_mm) -> TetMesh``.
Both raise :class:`MeshError` (a :class:`~dotshell.errors.DotshellError`) on bad input.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Protocol

import numpy as np

from dotshell.errors import DotshellError
from dotshell.fem.faces import boundary_faces_by_sorting  # noqa: F401 - re-exported


class MeshError(DotshellError):
    """A mesh cannot be made from the given input (too sparse, not closable, bad size)."""


@dataclass
class TriangleSurface:
    """Closed triangle surface: ``vertices`` (V, 3) mm, ``triangles`` (F, 3) int, outward."""

    vertices: np.ndarray
    triangles: np.ndarray

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, np.float64).reshape(-1, 3)
        self.triangles = np.asarray(self.triangles, np.int64).reshape(-1, 3)


@dataclass
class TetMesh:
    """Tetrahedral mesh: ``nodes`` (N, 3) mm, ``tets`` (M, 4) int 0-based, positively
    oriented. ``point_data`` holds per-node arrays (optical properties, region)."""

    nodes: np.ndarray
    tets: np.ndarray
    point_data: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        # C order whatever the caller's layout (a column-permuted array is Fortran-ordered):
        # the numba kernels are compiled for C-ordered arrays, and another layout would compile
        # a second variant of each (~3-5 s of CPU on first use)
        self.nodes = np.ascontiguousarray(np.reshape(self.nodes, (-1, 3)), np.float64)
        self.tets = np.ascontiguousarray(np.reshape(self.tets, (-1, 4)), np.int64)

    @cached_property
    def boundary_faces(self) -> np.ndarray:
        """Outward faces used by one tetrahedron (computed once: ``tets`` is not changed)."""
        return boundary_faces(self.tets)

    @cached_property
    def matrix_pattern(self) -> MatrixPattern:
        """Where linear-element matrices on this mesh have entries (computed once: ``tets``
        is not changed)."""
        return matrix_pattern(self.tets, self.boundary_faces, len(self.nodes))

    @property
    def boundary_nodes(self) -> np.ndarray:
        """(N,) bool: the node lies on the outer surface."""
        flag = np.zeros(len(self.nodes), bool)
        flag[self.boundary_faces.ravel()] = True
        return flag


@dataclass
class SurfaceResult:
    """A surface mesher's output: the closed surface and figures for the report."""

    surface: TriangleSurface
    stats: dict[str, Any] = field(default_factory=dict)


class SurfaceMesher(Protocol):
    def surface(self, points_mm: np.ndarray, viewpoints_mm: np.ndarray | None,
                node_distance_mm: float, bottom_z_mm: float | None) -> SurfaceResult:
        """Closed surface from a cloud (N, 3); ``viewpoints_mm`` (N, 3) the sensor position
        that saw each point (orients normals outward), ``bottom_z_mm`` the plane where an open
        bottom is closed (None = leave it to the reconstruction)."""
        ...


class VolumeMesher(Protocol):
    def volume(self, surface: TriangleSurface, node_distance_mm: float) -> TetMesh:
        """Tetrahedra filling a closed surface with about ``node_distance_mm`` between nodes."""
        ...


# ---- surfaces -----------------------------------------------------------------------------

def triangle_areas_mm2(surface: TriangleSurface) -> np.ndarray:
    v = surface.vertices[surface.triangles]
    return 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)


def enclosed_volume_mm3(surface: TriangleSurface) -> float:
    """Signed volume enclosed by a closed, outward-oriented surface (divergence theorem)."""
    v = surface.vertices[surface.triangles]
    return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)


def unique_values(values: np.ndarray) -> np.ndarray:
    """``np.unique(values)`` (sorted distinct values, flattened) for integer arrays, found by
    sorting. numpy ≥ 2.3 finds plain unique values with a hash table, which is 40-60x slower
    than a sort when most values are distinct (measured, numpy 2.4: 360 000 int64 keys of a
    tetrahedral mesh's edges 0.50 s against 0.008 s); with ``return_counts`` or
    ``return_inverse`` it sorts."""
    s = np.sort(np.ravel(values))
    if s.size == 0:
        return s
    return s[np.concatenate(([True], s[1:] != s[:-1]))]


def compact(nodes: np.ndarray, tets: np.ndarray) -> TetMesh:
    """The mesh of ``tets`` without the nodes no tetrahedron uses, renumbered (TetGen leaves
    the input surface's unused points in its output)."""
    used = unique_values(tets)
    remap = np.full(len(nodes), -1, np.int64)
    remap[used] = np.arange(len(used))
    return TetMesh(nodes[used], remap[tets])


def unique_rows(rows: np.ndarray, return_inverse: bool = False,
                return_counts: bool = False) -> tuple[np.ndarray, ...]:
    """``np.unique(rows, axis=0, return_inverse=..., return_counts=...)`` for rows of
    non-negative integers (node indices): the same rows in the same order, found as one int64
    key per row (numpy's row-wise unique compares the rows as bytes, about 5x slower on a
    Poisson surface's edges). Falls back to numpy's when the keys would not fit."""
    rows = np.asarray(rows)
    n_cols = rows.shape[1] if rows.ndim == 2 else 0
    base = int(rows.max()) + 1 if rows.size else 0
    if rows.size == 0 or rows.min() < 0 or base ** n_cols >= 1 << 62:
        # numpy's overloads take only literal True/False flags, not a bool variable
        return np.unique(rows, axis=0, return_inverse=return_inverse,  # type: ignore[call-overload]
                         return_counts=return_counts)
    keys = np.zeros(len(rows), np.int64)
    for j in range(n_cols):
        keys = keys * base + rows[:, j]
    found = (np.unique(keys, return_inverse=return_inverse, return_counts=return_counts)  # type: ignore[call-overload]
             if return_inverse or return_counts else (unique_values(keys),))
    cols, rest = [], found[0]
    for _ in range(n_cols):
        rest, col = np.divmod(rest, base)
        cols.append(col)
    return (np.column_stack(cols[::-1]).astype(rows.dtype), *found[1:])


def edge_use(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undirected edges (E, 2) and how many triangles use each."""
    e = np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    edges, counts = unique_rows(e, return_counts=True)
    return edges, counts


def closed_manifold_problems(surface: TriangleSurface) -> list[str]:
    """Why a surface is not a closed, consistently oriented 2-manifold ([] if it is)."""
    t = surface.triangles
    if len(t) == 0:
        return ["no triangles"]
    problems = []
    _, count = edge_use(t)
    if (count == 1).any():
        problems.append(f"{int((count == 1).sum())} boundary edges (holes)")
    if (count > 2).any():
        problems.append(f"{int((count > 2).sum())} edges shared by more than two triangles")
    directed = t[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    _, dcount = unique_rows(directed, return_counts=True)
    if (dcount > 1).any():
        problems.append(f"{int((dcount > 1).sum())} edges with inconsistent orientation")
    if not problems and enclosed_volume_mm3(surface) <= 0:
        problems.append("normals point inwards (negative enclosed volume)")
    return problems


# ---- tetrahedra ---------------------------------------------------------------------------

def signed_volumes_mm3(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """det[b − a, c − a, d − a] / 6 per tetrahedron (positive = positively oriented)."""
    p = nodes[tets]
    a = p[:, 0]
    return np.einsum("ij,ij->i", p[:, 1] - a, np.cross(p[:, 2] - a, p[:, 3] - a)) / 6.0


def orient_positive(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """A copy of ``tets`` with the last two nodes swapped wherever the volume is negative."""
    out = np.array(tets, np.int64, copy=True)
    neg = signed_volumes_mm3(nodes, out) < 0
    out[neg, 2], out[neg, 3] = tets[neg, 3], tets[neg, 2]
    return out


def boundary_faces(tets: np.ndarray) -> np.ndarray:
    """Faces (F, 3) used by exactly one tetrahedron, ordered so their normals point out of it
    (tets positively oriented)."""
    from dotshell.fem import kernels as fem_kernels  # numba: imported at first use

    tets = np.ascontiguousarray(np.reshape(tets, (-1, 4)), np.int64)  # C order: see TetMesh
    if len(tets) == 0:
        return np.empty((0, 3), np.int64)
    t, f = np.nonzero(fem_kernels.unshared_faces(tets, int(tets.max()) + 1))
    return tets[t[:, None], fem_kernels.TET_FACES[f]]


@dataclass(frozen=True)
class MatrixPattern:
    """Sparsity pattern (CSR, sorted rows) of linear-element matrices on a mesh — the node
    pairs that share a tetrahedron — and where each element's block goes in the data array:
    ``tet_slots`` (M, 4, 4) for the tetrahedra, ``face_slots`` (F, 3, 3) for the boundary
    faces (in :attr:`TetMesh.boundary_faces` order)."""

    indptr: np.ndarray
    indices: np.ndarray
    tet_slots: np.ndarray
    face_slots: np.ndarray

    @property
    def nnz(self) -> int:
        """Number of stored entries."""
        return len(self.indices)

    def matrix(self, data: np.ndarray) -> Any:
        """The (N, N) ``scipy.sparse.csr_matrix`` with this pattern and ``data`` (nnz,)."""
        import scipy.sparse as sp

        n = len(self.indptr) - 1
        return sp.csr_matrix((data, self.indices, self.indptr), shape=(n, n))


def matrix_pattern(tets: np.ndarray, faces: np.ndarray, n_nodes: int) -> MatrixPattern:
    """The :class:`MatrixPattern` of tetrahedra (M, 4) with boundary faces (F, 3) (faces of
    those tetrahedra) on ``n_nodes`` nodes."""
    from dotshell.fem import kernels as fem_kernels  # numba: imported at first use

    tets = np.asarray(tets).reshape(-1, 4)
    if 12 * len(tets) + n_nodes >= 2 ** 31:
        raise MeshError(f"a mesh of {len(tets)} tetrahedra is too large for the FEM assembly "
                        "(int32 indices); mesh with a larger node_distance_mm.")
    indptr, indices, tet_slots = fem_kernels.node_pairs_pattern(
        np.ascontiguousarray(tets, np.int32), n_nodes)  # C order: see TetMesh
    return MatrixPattern(indptr, indices, tet_slots,
                         fem_kernels.block_positions(indptr, indices, faces))


_EDGES = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))


def joe_liu_quality(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Joe–Liu quality ``12 (3|V|)^(2/3) / Σ l²`` (1 = regular tetrahedron, 0 = flat)."""
    p = nodes[tets]
    l2 = sum(np.sum((p[:, i] - p[:, j]) ** 2, axis=1) for i, j in _EDGES)
    v = np.abs(signed_volumes_mm3(nodes, tets))
    return 12.0 * np.cbrt(3.0 * v) ** 2 / np.maximum(l2, 1e-300)


def min_dihedral_deg(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Smallest of the six interior dihedral angles of each tetrahedron, degrees."""
    p = nodes[tets]
    out = np.full(len(tets), 180.0)
    for i, j in _EDGES:
        k, m = (n for n in range(4) if n not in (i, j))
        e = p[:, j] - p[:, i]
        e = e / np.maximum(np.linalg.norm(e, axis=1, keepdims=True), 1e-300)
        # the two faces along edge ij: their in-face directions perpendicular to the edge
        u = p[:, k] - p[:, i]
        w = p[:, m] - p[:, i]
        u = u - e * np.einsum("ij,ij->i", u, e)[:, None]
        w = w - e * np.einsum("ij,ij->i", w, e)[:, None]
        cos = np.einsum("ij,ij->i", u, w) / np.maximum(
            np.linalg.norm(u, axis=1) * np.linalg.norm(w, axis=1), 1e-300)
        out = np.minimum(out, np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    return out


def quality_report(mesh: TetMesh, surface: TriangleSurface | None = None) -> dict[str, Any]:
    """Element count, Joe–Liu min/mean, minimum dihedral angle, inverted elements and the total
    volume against the surface's enclosed volume."""
    vol = signed_volumes_mm3(mesh.nodes, mesh.tets)
    q = joe_liu_quality(mesh.nodes, mesh.tets)
    out: dict[str, Any] = {
        "nodes": int(len(mesh.nodes)),
        "elements": int(len(mesh.tets)),
        "boundary_nodes": int(mesh.boundary_nodes.sum()),
        "boundary_faces": int(len(mesh.boundary_faces)),
        "inverted_elements": int((vol <= 0).sum()),
        "joe_liu_min": float(q.min()),
        "joe_liu_mean": float(q.mean()),
        "min_dihedral_deg": float(min_dihedral_deg(mesh.nodes, mesh.tets).min()),
        "volume_mm3": float(vol.sum()),
    }
    edges, = unique_rows(np.sort(mesh.tets[:, [0, 1, 0, 2, 0, 3, 1, 2, 1, 3, 2, 3]]
                                 .reshape(-1, 2), axis=1))
    lengths = np.linalg.norm(mesh.nodes[edges[:, 0]] - mesh.nodes[edges[:, 1]], axis=1)
    out["edge_length_mm"] = {"mean": float(lengths.mean()), "median": float(np.median(lengths)),
                             "min": float(lengths.min()), "max": float(lengths.max())}
    if surface is not None:
        sv = enclosed_volume_mm3(surface)
        out["surface_volume_mm3"] = sv
        out["volume_vs_surface_pct"] = 100.0 * (out["volume_mm3"] - sv) / sv if sv else None
    return out


def element_containing(mesh: TetMesh, point_mm: np.ndarray) -> tuple[int, np.ndarray]:
    """Index of the tetrahedron containing ``point_mm`` and its barycentric weights (4,).

    Raises:
        MeshError: the point is outside the mesh.
    """
    from dotshell.fem.kernels import boxes_holding  # numba: imported at first use

    point = np.asarray(point_mm, float).reshape(3)
    near = boxes_holding(mesh.nodes, mesh.tets, point, 1e-6)
    p = mesh.nodes[mesh.tets[near]]  # the tetrahedra whose bounding box holds the point
    T = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2)
    rhs = point[None, :] - p[:, 0]
    ok = np.abs(np.linalg.det(T)) > 1e-12
    lam = np.full((len(p), 3), -1.0)
    lam[ok] = np.linalg.solve(T[ok], rhs[ok][..., None])[..., 0]
    w = np.column_stack([1.0 - lam.sum(axis=1), lam])
    inside = np.where((w >= -1e-9).all(axis=1))[0]
    if len(inside) == 0:
        raise MeshError(f"point {np.round(point_mm, 3).tolist()} mm is outside the mesh; give a "
                        "source position inside the volume (sample frame, mm).")
    k = int(inside[0])
    return int(near[k]), w[k]
