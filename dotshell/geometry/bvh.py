"""Closest-point queries and ray casts on a triangle mesh through a bounding volume hierarchy
(compiled with numba), in float64. Coordinates in mm.

Why not open3d's ``RaycastingScene`` (:mod:`dotshell.geometry.raycast`): loading open3d costs a
process ~145 MiB of resident libraries, and the scan process needed it only for these two
queries (the simulator's trans-illumination truth, the normalization's mapping), which kept the
agar scan above its 1 GB bound (docs/performance.md, "The agar profile (issue 33)"). The
answers are open3d's to float32 rounding (open3d computes in float32; here float64), in the
same form: hits' triangle ids, barycentric ``uv`` (the point is ``(1 - u - v) a + u b + v c``
for the triangle's corners ``a b c``) and unit face normals ``(b - a) × (c - a)``.

The tree: each node a box around its triangles; a node of more than :data:`LEAF_SIZE`
triangles is split at the median of their centroids along the box's longest side (balanced:
depth ~log2(T / LEAF_SIZE), well inside the traversal stack). Queries visit the nearer child
first and skip boxes farther than the best answer so far.
"""

from __future__ import annotations

import numba
import numpy as np

from dotshell.geometry.raycast import ClosestPoints, barycentric_weights
from dotshell.runtime import numba_cache

numba_cache.install()  # cache files safe for processes compiling at once

#: triangles in a leaf at most
LEAF_SIZE = 4
#: traversal stack depth (a balanced tree of 2**40 leaves fits)
_STACK = 96

_OPTS: dict = dict(nogil=True, cache=True, error_model="numpy")


@numba.njit(**_OPTS)
def _build(vertices: np.ndarray, triangles: np.ndarray, leaf_size: int
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The tree of ``triangles`` (T, 3): per node its box ``lo``, ``hi`` (n, 3), first child
    ``left`` (its sibling is ``left + 1``; -1 for a leaf) and its triangles
    ``order[start:start + count]``."""
    n_tri = len(triangles)
    cent = np.empty((n_tri, 3))
    for t in range(n_tri):
        for d in range(3):
            cent[t, d] = (vertices[triangles[t, 0], d] + vertices[triangles[t, 1], d]
                          + vertices[triangles[t, 2], d]) / 3.0
    cap = max(2 * n_tri, 1)
    lo = np.empty((cap, 3))
    hi = np.empty((cap, 3))
    left = np.full(cap, -1, np.int64)
    start = np.zeros(cap, np.int64)
    count = np.zeros(cap, np.int64)
    order = np.arange(n_tri)
    count[0] = n_tri
    n_nodes = 1
    stack = [0]
    while len(stack):
        node = stack.pop()
        s, c = start[node], count[node]
        for d in range(3):
            lo[node, d] = np.inf
            hi[node, d] = -np.inf
        clo = np.full(3, np.inf)
        chi = np.full(3, -np.inf)
        for k in range(s, s + c):
            t = order[k]
            for d in range(3):
                clo[d] = min(clo[d], cent[t, d])
                chi[d] = max(chi[d], cent[t, d])
                for j in range(3):
                    x = vertices[triangles[t, j], d]
                    lo[node, d] = min(lo[node, d], x)
                    hi[node, d] = max(hi[node, d], x)
        if c <= leaf_size:
            continue
        axis = np.argmax(chi - clo)
        part = order[s:s + c]
        order[s:s + c] = part[np.argsort(cent[part, axis], kind="mergesort")]
        half = c // 2
        left[node] = n_nodes
        start[n_nodes], count[n_nodes] = s, half
        start[n_nodes + 1], count[n_nodes + 1] = s + half, c - half
        stack.append(n_nodes)
        stack.append(n_nodes + 1)
        n_nodes += 2
    return lo[:n_nodes].copy(), hi[:n_nodes].copy(), left[:n_nodes].copy(), \
        start[:n_nodes].copy(), count[:n_nodes].copy(), order


@numba.njit(nogil=True, cache=True, inline="always")
def _push_children(stack: np.ndarray, top: int, first: int, first_is_nearer: bool) -> int:
    """Push a node's two children (``first``, ``first + 1``) on the traversal stack, the
    nearer last so that it is visited first; the new stack height."""
    near, far = (first, first + 1) if first_is_nearer else (first + 1, first)
    stack[top] = far
    stack[top + 1] = near
    return top + 2


@numba.njit(nogil=True, cache=True, inline="always")
def _box_distance2(p: np.ndarray, lo: np.ndarray, hi: np.ndarray, node: int) -> float:
    """Squared distance (mm²) from point ``p`` to a node's box (0 inside)."""
    d2 = 0.0
    for d in range(3):
        if p[d] < lo[node, d]:
            d2 += (lo[node, d] - p[d]) ** 2
        elif p[d] > hi[node, d]:
            d2 += (p[d] - hi[node, d]) ** 2
    return d2


@numba.njit(nogil=True, cache=True, inline="always")
def _closest_on_triangle(p: np.ndarray, vertices: np.ndarray, tri: np.ndarray
                         ) -> tuple[float, float]:
    """Barycentric (u, v) of the point of triangle ``tri`` (corners ``a b c``) closest to
    ``p`` (``a + u (b - a) + v (c - a)``), by the Voronoi region of ``p``: a corner, an edge
    or the inside. Scalar arithmetic: no arrays made per triangle."""
    a, b, c = vertices[tri[0]], vertices[tri[1]], vertices[tri[2]]
    d1 = d2 = d3 = d4 = d5 = d6 = 0.0
    for k in range(3):
        ab, ac = b[k] - a[k], c[k] - a[k]
        d1 += ab * (p[k] - a[k])
        d2 += ac * (p[k] - a[k])
        d3 += ab * (p[k] - b[k])
        d4 += ac * (p[k] - b[k])
        d5 += ab * (p[k] - c[k])
        d6 += ac * (p[k] - c[k])
    if d1 <= 0.0 and d2 <= 0.0:
        return 0.0, 0.0
    if d3 >= 0.0 and d4 <= d3:
        return 1.0, 0.0
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        return d1 / (d1 - d3), 0.0
    if d6 >= 0.0 and d5 <= d6:
        return 0.0, 1.0
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        return 0.0, d2 / (d2 - d6)
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return 1.0 - w, w
    denom = 1.0 / (va + vb + vc)
    return vb * denom, vc * denom


@numba.njit(nogil=True, cache=True, inline="always")
def _distance2(p: np.ndarray, vertices: np.ndarray, tri: np.ndarray, u: float, v: float
               ) -> float:
    """Squared distance (mm²) from ``p`` to the point (u, v) of triangle ``tri``."""
    a, b, c = vertices[tri[0]], vertices[tri[1]], vertices[tri[2]]
    d2 = 0.0
    for k in range(3):
        d2 += (p[k] - (a[k] + u * (b[k] - a[k]) + v * (c[k] - a[k]))) ** 2
    return d2


@numba.njit(**_OPTS)
def _closest(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray, lo: np.ndarray,
             hi: np.ndarray, left: np.ndarray, start: np.ndarray, count: np.ndarray,
             order: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each point (N, 3): the closest surface point (N, 3), its triangle (N,) and its
    barycentric ``uv`` (N, 2)."""
    n = len(points)
    out = np.empty((n, 3))
    tri = np.empty(n, np.int64)
    uv = np.empty((n, 2))
    stack = np.empty(_STACK, np.int64)
    for i in range(n):
        p = points[i]
        best, best_t, bu, bv = np.inf, 0, 0.0, 0.0
        if i > 0:  # neighbouring points (image order) share triangles: a tight bound at once
            best_t = tri[i - 1]
            bu, bv = _closest_on_triangle(p, vertices, triangles[best_t])
            best = _distance2(p, vertices, triangles[best_t], bu, bv)
            if not best < np.inf:  # NaN: a degenerate triangle gives no bound
                best = np.inf
        stack[0] = 0
        top = 1
        while top:
            top -= 1
            node = stack[top]
            if _box_distance2(p, lo, hi, node) >= best:
                continue
            first = left[node]
            if first < 0:
                for k in range(start[node], start[node] + count[node]):
                    t = order[k]
                    u, v = _closest_on_triangle(p, vertices, triangles[t])
                    d2 = _distance2(p, vertices, triangles[t], u, v)
                    if d2 < best:
                        best, best_t, bu, bv = d2, t, u, v
                continue
            d_first = _box_distance2(p, lo, hi, first)
            d_second = _box_distance2(p, lo, hi, first + 1)
            top = _push_children(stack, top, first, d_first <= d_second)
        a, b, c = vertices[triangles[best_t, 0]], vertices[triangles[best_t, 1]], \
            vertices[triangles[best_t, 2]]
        for k in range(3):
            out[i, k] = a[k] + bu * (b[k] - a[k]) + bv * (c[k] - a[k])
        tri[i], uv[i, 0], uv[i, 1] = best_t, bu, bv
    return out, tri, uv


@numba.njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _box_entry(o: np.ndarray, inv: np.ndarray, lo: np.ndarray, hi: np.ndarray, node: int,
               t_max: float) -> float:
    """Ray parameter at which the ray enters a node's box (inf if it misses it before
    ``t_max``); slab test with the direction's inverse ``inv`` (inf for zero components)."""
    t0, t1 = 0.0, t_max
    for d in range(3):
        a = (lo[node, d] - o[d]) * inv[d]
        b = (hi[node, d] - o[d]) * inv[d]
        if a != a:  # 0 * inf: the ray lies in the slab's plane
            a = -np.inf
        if b != b:
            b = np.inf
        if a > b:
            a, b = b, a
        t0, t1 = max(t0, a), min(t1, b)
        if t0 > t1:
            return np.inf
    return t0


@numba.njit(nogil=True, cache=True, inline="always", error_model="numpy")
def _ray_triangle(o: np.ndarray, dr: np.ndarray, vertices: np.ndarray, tri: np.ndarray
                  ) -> tuple[float, float, float]:
    """(t, u, v) where the ray meets triangle ``tri`` (Möller-Trumbore; either side), t = inf
    where it does not."""
    a, b, c = vertices[tri[0]], vertices[tri[1]], vertices[tri[2]]
    e1x, e1y, e1z = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    e2x, e2y, e2z = c[0] - a[0], c[1] - a[1], c[2] - a[2]
    px, py, pz = dr[1] * e2z - dr[2] * e2y, dr[2] * e2x - dr[0] * e2z, dr[0] * e2y - dr[1] * e2x
    det = e1x * px + e1y * py + e1z * pz
    if det == 0.0:
        return np.inf, 0.0, 0.0  # the ray is parallel to the triangle's plane
    f = 1.0 / det
    sx, sy, sz = o[0] - a[0], o[1] - a[1], o[2] - a[2]
    u = f * (sx * px + sy * py + sz * pz)
    if u < 0.0 or u > 1.0:
        return np.inf, 0.0, 0.0
    qx, qy, qz = sy * e1z - sz * e1y, sz * e1x - sx * e1z, sx * e1y - sy * e1x
    v = f * (dr[0] * qx + dr[1] * qy + dr[2] * qz)
    if v < 0.0 or u + v > 1.0:
        return np.inf, 0.0, 0.0
    return f * (e2x * qx + e2y * qy + e2z * qz), u, v


@numba.njit(**_OPTS)
def _cast(origins: np.ndarray, dirs: np.ndarray, vertices: np.ndarray, triangles: np.ndarray,
          lo: np.ndarray, hi: np.ndarray, left: np.ndarray, start: np.ndarray,
          count: np.ndarray, order: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First hits (t > 0, either side of a triangle) of rays (N, 3) origins and directions:
    ``t`` (N,) in units of the direction's length (inf: none), triangle (N,) (-1: none) and
    barycentric ``uv`` (N, 2)."""
    n = len(origins)
    t_hit = np.full(n, np.inf)
    tri = np.full(n, -1, np.int64)
    uv = np.zeros((n, 2))
    stack = np.empty(_STACK, np.int64)
    inv = np.empty(3)
    for i in range(n):
        o, dr = origins[i], dirs[i]
        for d in range(3):
            inv[d] = 1.0 / dr[d]
        best = np.inf
        stack[0] = 0
        top = 1
        while top:
            top -= 1
            node = stack[top]
            if _box_entry(o, inv, lo, hi, node, best) == np.inf:
                continue
            first = left[node]
            if first >= 0:
                e_first = _box_entry(o, inv, lo, hi, first, best)
                e_second = _box_entry(o, inv, lo, hi, first + 1, best)
                top = _push_children(stack, top, first, e_first <= e_second)
                continue
            for k in range(start[node], start[node] + count[node]):
                th, u, v = _ray_triangle(o, dr, vertices, triangles[order[k]])
                if 0.0 < th < best:
                    best = th
                    t_hit[i], tri[i], uv[i, 0], uv[i, 1] = th, order[k], u, v
    return t_hit, tri, uv


class TriangleBVH:
    """A triangle mesh (vertices (V, 3) mm, triangles (T, 3) indices) ready for closest-point
    queries and ray casts; the same answers as :class:`dotshell.geometry.raycast.TriangleScene`
    (open3d) to float32 rounding, without loading open3d."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray) -> None:
        self.vertices = np.ascontiguousarray(vertices, np.float64)
        self.triangles = np.ascontiguousarray(triangles, np.int64)
        if len(self.triangles) == 0:
            raise ValueError("a triangle mesh without triangles has no closest points or hits")
        self._tree = _build(self.vertices, self.triangles, LEAF_SIZE)
        corners = self.vertices[self.triangles]
        normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        # unit face normals, and a row of zeros (index -1) for rays that hit nothing
        self._normals = np.zeros((len(normals) + 1, 3))
        self._normals[:-1] = normals / np.maximum(np.linalg.norm(normals, axis=1,
                                                                 keepdims=True), 1e-300)

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> dict[str, np.ndarray]:
        """First hits of rays (N, 3) origins and (N, 3) directions: ``t_hit`` (inf = miss; in
        units of the direction's length), ``primitive_ids`` (-1 = miss), ``primitive_uvs``
        (N, 2) and unit ``primitive_normals`` (N, 3; zeros for a miss), as open3d names them."""
        o = np.ascontiguousarray(np.broadcast_to(origins, np.shape(dirs)), np.float64)
        d = np.ascontiguousarray(dirs, np.float64)
        t_hit, tri, uv = _cast(o, d, self.vertices, self.triangles, *self._tree)
        return {"t_hit": t_hit, "primitive_ids": tri, "primitive_uvs": uv,
                "primitive_normals": self._normals[tri]}

    def closest(self, points: np.ndarray) -> ClosestPoints:
        """The closest surface point to each of ``points`` (N, 3)."""
        p = np.ascontiguousarray(np.asarray(points, np.float64).reshape(-1, 3))
        closest, tri, uv = _closest(p, self.vertices, self.triangles, *self._tree)
        return ClosestPoints(self.triangles[tri], barycentric_weights(uv), closest,
                             np.linalg.norm(p - closest, axis=1))
