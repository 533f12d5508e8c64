"""Compiled loops (numba) of the finite-element assembly: boundary faces, the sparsity pattern
of a tetrahedral mesh with the position of every element's entries in it, the diffusion
element matrices added into a matrix's data array, and the tetrahedra near a point.

Why compiled (docs/performance.md, "Forward solve"): assembling the system of a 31 k-node mesh
with numpy took ~0.7 s of CPU — an ``np.unique`` sort of 700 k face keys for the boundary,
(M, 3)-sized temporaries per cross product for the gradients, and a COO → CSR conversion that
sorts 2.9 M entries to sum duplicates — against a CG solve of ~0.2 s. Here every pass is linear
in the mesh size: faces are grouped by their smallest node (a counting sort), the pattern is
built node by node from the tetrahedra around each node, and each element's matrix is computed
and added into the CSR data array at positions found once per mesh, in one pass. The meshes'
node numbering (TetGen's) has no locality, so these loops are bound by scattered memory reads:
they read and write int32 where int64 is not needed, and copy each node's tetrahedra next to
each other.

:mod:`dotshell.fem.meshes` and :mod:`dotshell.fem.forward` import this module at first use: numba's import
costs ~0.5 s, which code that only reads meshes doesn't pay. ``cache=True`` keeps the compiled
code in ``__pycache__`` (the first compile takes ~8 s); a process still pays numba's
initialization, ~0.6 s, at its first compiled call.
"""

from __future__ import annotations

import numba
import numpy as np

from dotshell.fem.faces import TET_FACES  # the faces' order, shared with the numpy code
from dotshell.runtime import numba_cache

numba_cache.install()  # cache files safe for processes compiling at once

_OPTS: dict = dict(nogil=True, cache=True)  # dict, not dict[str, bool]: njit's keywords differ in type


@numba.njit(**_OPTS)
def _tets_by_node(tets: np.ndarray, n_nodes: int
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tetrahedra around each node, by a counting sort of ``tets``' (M, 4) entries: for
    the k-th use, ``use[k]`` = 4 t + a (node a of tetrahedron t) and ``around[k]`` the four
    nodes of t (copied, so that a node's tetrahedra are read contiguously); those of node i
    are at ``start[i]:start[i + 1]``."""
    start = np.zeros(n_nodes + 1, np.int64)
    for j in tets.ravel():
        start[j + 1] += 1
    for i in range(n_nodes):
        start[i + 1] += start[i]
    fill = start[:-1].copy()
    use = np.empty(tets.size, np.int32)
    around = np.empty((tets.size, 4), np.int32)
    for t in range(len(tets)):
        for a in range(4):
            k = fill[tets[t, a]]
            fill[tets[t, a]] += 1
            use[k] = 4 * t + a
            for b in range(4):
                around[k, b] = tets[t, b]
    return use, around, start


@numba.njit(**_OPTS)
def _face_nodes(tets: np.ndarray, t: int, f: int) -> tuple[int, int, int]:
    """The nodes of face ``f`` (:data:`TET_FACES`) of tetrahedron ``t``, smallest first."""
    a, b, c = tets[t, TET_FACES[f, 0]], tets[t, TET_FACES[f, 1]], tets[t, TET_FACES[f, 2]]
    lo, hi = min(a, min(b, c)), max(a, max(b, c))
    return lo, a + b + c - lo - hi, hi


@numba.njit(**_OPTS)
def unshared_faces(tets: np.ndarray, n_nodes: int) -> np.ndarray:
    """(M, 4) bool: face f (:data:`TET_FACES` order) of tetrahedron t belongs to no other
    tetrahedron — the boundary (``tets`` (M, 4) on ``n_nodes`` nodes). Faces are grouped by
    their smallest node (a counting sort that moves each face's other two nodes, packed in one
    int64, next to its group's) and compared within the group."""
    m = len(tets)
    start = np.zeros(n_nodes + 1, np.int64)
    for t in range(m):
        for f in range(4):
            start[_face_nodes(tets, t, f)[0] + 1] += 1
    for i in range(n_nodes):
        start[i + 1] += start[i]
    fill = start[:-1].copy()
    rest = np.empty(4 * m, np.int64)  # mid × n_nodes + hi, grouped by the smallest node
    face = np.empty(4 * m, np.int32)  # 4 t + f
    for t in range(m):
        for f in range(4):
            lo, mid, hi = _face_nodes(tets, t, f)
            rest[fill[lo]] = mid * n_nodes + hi
            face[fill[lo]] = 4 * t + f
            fill[lo] += 1
    alone = np.ones(4 * m, np.bool_)
    for node in range(n_nodes):
        for i in range(start[node], start[node + 1]):
            for j in range(i + 1, start[node + 1]):
                if rest[i] == rest[j]:
                    alone[face[i]] = False
                    alone[face[j]] = False
    return alone.reshape(m, 4)


@numba.njit(**_OPTS)
def node_pairs_pattern(tets: np.ndarray, n_nodes: int
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """CSR sparsity pattern of the node pairs that share a tetrahedron of ``tets`` (M, 4), the
    diagonal included — the nonzeros of any linear-element matrix on the mesh: ``indptr``
    (N + 1,), ``indices`` (sorted within each row), and ``slots`` (M, 4, 4), the position in
    ``indices`` (and so in the data array) of entry (tets[t, a], tets[t, b]).

    Built row by row from the tetrahedra around each node (a row of node i has at most
    1 + 3 × its tetrahedra entries), each new column inserted in order. Indices and
    positions are int32 (half the memory traffic of int64; scipy's own choice for matrices
    of fewer than 2³¹ entries): ``tets`` int32, with 12 M + N < 2³¹."""
    use, around, start = _tets_by_node(tets, n_nodes)
    seen = np.full(n_nodes, -1, np.int32)
    where = np.empty(n_nodes, np.int32)  # position of each column of the current row
    indptr = np.zeros(n_nodes + 1, np.int32)
    indices = np.empty(3 * len(use) + n_nodes, np.int32)
    slots = np.empty((len(tets), 4, 4), np.int32)
    end = 0
    for node in range(n_nodes):
        row = end
        for k in range(start[node], start[node + 1]):
            for j in around[k]:
                if seen[j] != node:
                    seen[j] = node
                    p = end
                    while p > row and indices[p - 1] > j:
                        indices[p] = indices[p - 1]
                        p -= 1
                    indices[p] = j
                    end += 1
        for p in range(row, end):
            where[indices[p]] = p
        for k in range(start[node], start[node + 1]):
            t, a = use[k] // 4, use[k] % 4
            for b in range(4):
                slots[t, a, b] = where[around[k, b]]
        indptr[node + 1] = end
    return indptr, indices[:end].copy(), slots


@numba.njit(**_OPTS)
def block_positions(indptr: np.ndarray, indices: np.ndarray, elements: np.ndarray) -> np.ndarray:
    """(E, k, k) positions in ``indices`` (and so in the data array) of the entries
    (elements[e, i], elements[e, j]) of each element's k × k block, in a CSR pattern with
    sorted rows (binary search in the row); -1 where the pattern lacks the entry."""
    n, k = elements.shape
    out = np.empty((n, k, k), np.int32)
    for e in range(n):
        for i in range(k):
            row = elements[e, i]
            for j in range(k):
                col = elements[e, j]
                lo, hi = indptr[row], indptr[row + 1]
                while lo < hi:
                    m = (lo + hi) // 2
                    if indices[m] < col:
                        lo = m + 1
                    else:
                        hi = m
                found = lo < indptr[row + 1] and indices[lo] == col
                out[e, i, j] = lo if found else -1
    return out


@numba.njit(**_OPTS)
def boxes_holding(nodes: np.ndarray, tets: np.ndarray, point: np.ndarray,
                  margin: float) -> np.ndarray:
    """Indices (ascending) of the tetrahedra whose bounding box, grown by ``margin`` (mm),
    holds ``point`` (3,) mm."""
    out = np.empty(len(tets), np.int64)
    count = 0
    for t in range(len(tets)):
        inside = True
        for c in range(3):
            lo = min(min(nodes[tets[t, 0], c], nodes[tets[t, 1], c]),
                     min(nodes[tets[t, 2], c], nodes[tets[t, 3], c]))
            hi = max(max(nodes[tets[t, 0], c], nodes[tets[t, 1], c]),
                     max(nodes[tets[t, 2], c], nodes[tets[t, 3], c]))
            if lo > point[c] + margin or hi < point[c] - margin:
                inside = False
                break
        if inside:
            out[count] = t
            count += 1
    return out[:count].copy()


@numba.njit(nogil=True, cache=True, inline="always")
def _shape_gradients(nodes: np.ndarray, tet: np.ndarray, grad: np.ndarray) -> float:
    """Fill ``grad`` (4, 3) with the gradients of the tetrahedron's four linear shape
    functions (1/mm); return its signed volume (mm³). With e1, e2, e3 the edges from node 0
    (the rows of the Jacobian J), ∇λ1..λ3 are the columns of J⁻¹: (e2 × e3, e3 × e1,
    e1 × e2) / det J, and ∇λ0 is minus their sum."""
    p0 = nodes[tet[0]]
    x1, y1, z1 = nodes[tet[1], 0] - p0[0], nodes[tet[1], 1] - p0[1], nodes[tet[1], 2] - p0[2]
    x2, y2, z2 = nodes[tet[2], 0] - p0[0], nodes[tet[2], 1] - p0[1], nodes[tet[2], 2] - p0[2]
    x3, y3, z3 = nodes[tet[3], 0] - p0[0], nodes[tet[3], 1] - p0[1], nodes[tet[3], 2] - p0[2]
    grad[1, 0], grad[1, 1], grad[1, 2] = y2 * z3 - z2 * y3, z2 * x3 - x2 * z3, x2 * y3 - y2 * x3
    grad[2, 0], grad[2, 1], grad[2, 2] = y3 * z1 - z3 * y1, z3 * x1 - x3 * z1, x3 * y1 - y3 * x1
    grad[3, 0], grad[3, 1], grad[3, 2] = y1 * z2 - z1 * y2, z1 * x2 - x1 * z2, x1 * y2 - y1 * x2
    det = x1 * grad[1, 0] + y1 * grad[1, 1] + z1 * grad[1, 2]
    for c in range(3):
        grad[0, c] = 0.0
        for k in range(1, 4):
            grad[k, c] /= det
            grad[0, c] -= grad[k, c]
    return det / 6.0


@numba.njit(**_OPTS)
def add_diffusion_elements(data: np.ndarray, slots: np.ndarray, nodes: np.ndarray,
                           tets: np.ndarray, kappa: np.ndarray, mua: np.ndarray) -> int:
    """Add each tetrahedron's stiffness + mass ``κ̄ V ∇λa·∇λb + μ̄a V (1 + δab) / 20`` to the
    CSR ``data`` at ``slots`` (M, 4, 4) (from :func:`node_pairs_pattern`), with κ̄ (mm) and
    μ̄a (1/mm) the means of the per-node ``kappa`` and ``mua`` over its four nodes, V its
    volume (mm³) and λ its linear shape functions (``nodes`` in mm). Returns the number of
    inverted or flat tetrahedra (V ≤ 0), whose terms are meaningless."""
    grad = np.empty((4, 3))
    bad = 0
    for t in range(len(tets)):
        vol = _shape_gradients(nodes, tets[t], grad)
        if vol <= 0.0:
            bad += 1
        k_mean = 0.0
        mua_mean = 0.0
        for a in range(4):
            k_mean += kappa[tets[t, a]]
            mua_mean += mua[tets[t, a]]
        kv = k_mean / 4.0 * vol
        mv = mua_mean / 4.0 * vol / 20.0
        for a in range(4):
            for b in range(4):
                dot = 0.0
                for c in range(3):
                    dot += grad[a, c] * grad[b, c]
                data[slots[t, a, b]] += kv * dot + (2.0 * mv if a == b else mv)
    return bad
