"""The faces of tetrahedra with numpy alone (no numba): the face order the FEM kernels use, and
the boundary of a set of tetrahedra by sorting (:func:`dotshell.fem.meshes.boundary_faces`
counts them in a compiled pass instead)."""

from __future__ import annotations

import numpy as np

#: the four faces of a positively oriented tetrahedron (a, b, c, d), each ordered so its
#: right-hand normal points out of it: opposite to d, c, a, b
TET_FACES = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]], np.int64)


def boundary_faces_by_sorting(tets: np.ndarray) -> np.ndarray:
    """:func:`~dotshell.fem.meshes.boundary_faces` with numpy (the faces' sorted node triples sorted), the same
    faces in the same order, for a process that has not started numba: numba's first compiled
    call costs ~0.6 s of CPU, sorting the 250 k faces of the demo's 62 k tetrahedra ~0.03 s
    (the mesh process, the previews; issue 32)."""
    tets = np.ascontiguousarray(np.reshape(tets, (-1, 4)), np.int64)
    if len(tets) == 0:
        return np.empty((0, 3), np.int64)
    t, f = np.nonzero(unshared_faces(tets))
    return tets[t[:, None], TET_FACES[f]]


def unshared_faces(tets: np.ndarray) -> np.ndarray:
    """(M, 4) bool: face ``f`` (:data:`TET_FACES` order) of tetrahedron ``t`` is used by no
    other tetrahedron of ``tets`` (M, 4), found by sorting the faces' sorted node triples."""
    tets = np.ascontiguousarray(np.reshape(tets, (-1, 4)), np.int64)
    if len(tets) == 0:
        return np.zeros((0, 4), bool)
    faces = np.sort(tets[:, TET_FACES], axis=2).reshape(-1, 3)  # (4 M, 3), tet by tet
    n = int(tets.max()) + 1
    if n < 2_000_000:  # n³ fits an int64: one key per face, equal keys for equal faces
        keys = (faces[:, 0] * n + faces[:, 1]) * n + faces[:, 2]
        # the order among equal faces does not matter (both are marked shared): numpy's
        # default sort, 27 ms with the keys compared against 40 ms stable with the rows
        order = np.argsort(keys)
        k = keys[order]
        same = k[1:] == k[:-1]  # a face equal to its neighbour in sorted order
    else:
        order = np.lexsort((faces[:, 2], faces[:, 1], faces[:, 0]))
        s = faces[order]
        same = (s[1:] == s[:-1]).all(axis=1)
    shared = np.zeros(len(order), bool)
    shared[1:] |= same
    shared[:-1] |= same
    unshared = np.empty(len(order), bool)
    unshared[order] = ~shared
    return unshared.reshape(-1, 4)
