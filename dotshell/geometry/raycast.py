"""Ray casting and closest-point queries on a triangle mesh (open3d ``RaycastingScene``), with
the hit's triangle and barycentric weights, which is what mapping values between a mesh and
images or points needs. Coordinates in mm; open3d computes in float32 (~1e-5 mm at 200 mm).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dotshell.runtime.compat import import_open3d


class TriangleScene:
    """A triangle mesh ready for ray casting and closest-point queries."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray) -> None:
        self._o3d = import_open3d()
        self.triangles = np.asarray(triangles, np.int64)
        self._scene = self._o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(self._o3d.core.Tensor(np.asarray(vertices, np.float32)),
                                  self._o3d.core.Tensor(self.triangles.astype(np.uint32)))

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> dict[str, np.ndarray]:
        """First hits of rays (N, 3) origins and (N, 3) directions: ``t_hit`` (inf = miss; in
        units of the direction's length), ``primitive_ids``, ``primitive_uvs``,
        ``primitive_normals`` (open3d's arrays as numpy)."""
        rays = np.empty((len(dirs), 6), np.float32)
        rays[:, :3] = origins
        rays[:, 3:] = dirs
        hit = self._scene.cast_rays(self._o3d.core.Tensor(rays))
        return {k: hit[k].numpy() for k in ("t_hit", "primitive_ids", "primitive_uvs",
                                            "primitive_normals")}

    def closest(self, points: np.ndarray) -> ClosestPoints:
        """The closest surface point to each of ``points`` (N, 3)."""
        p = np.asarray(points, float).reshape(-1, 3)
        ans = self._scene.compute_closest_points(self._o3d.core.Tensor(p.astype(np.float32)))
        closest = ans["points"].numpy().astype(float)
        tri = self.triangles[ans["primitive_ids"].numpy().astype(np.int64)]
        return ClosestPoints(tri, barycentric_weights(ans["primitive_uvs"].numpy()), closest,
                             np.linalg.norm(p - closest, axis=1))


@dataclass
class ClosestPoints:
    """Closest surface points: the corner nodes (N, 3) of their triangles, barycentric weights
    (N, 3) of the point in it, the points (N, 3) mm and their distances (N,) mm."""

    nodes: np.ndarray
    weights: np.ndarray
    points: np.ndarray
    distance_mm: np.ndarray

    def interpolate(self, node_values: np.ndarray) -> np.ndarray:
        """Per-node values interpolated at the closest points (NaN where a corner has none)."""
        return np.einsum("ij,ij->i", node_values[self.nodes], self.weights)


def barycentric_weights(uv: np.ndarray) -> np.ndarray:
    """Weights (N, 3) of a triangle's corners from open3d's ``primitive_uvs`` (N, 2), clipped to
    the triangle (float32 rounding can push them just outside) and summing to 1."""
    uv = np.asarray(uv, float)
    w = np.clip(np.column_stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]]), 0.0, None)
    return w / np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
