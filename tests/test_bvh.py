"""The numba triangle hierarchy (:class:`dotshell.geometry.bvh.TriangleBVH`) gives open3d's
answers (:class:`dotshell.geometry.raycast.TriangleScene`) to its float32 rounding: the closest
points and their distances, ray hits, their triangles, barycentric weights and normals. It
replaced open3d in the scan process (the simulator's trans-illumination truth, the
normalization's mapping; issue 33), so a wrong answer here changes those figures."""

from __future__ import annotations

import numpy as np
import pytest

from dotshell.geometry.bvh import TriangleBVH
from dotshell.geometry.raycast import TriangleScene


@pytest.fixture(scope="module")
def bumpy_sphere() -> tuple[np.ndarray, np.ndarray]:
    """A closed sphere of radius 15 mm, ~3.2 k triangles, its vertices moved by up to ~0.1 mm
    (no two faces coplanar, no symmetry to hide a wrong traversal)."""
    pv = pytest.importorskip("pyvista")
    sphere = pv.Sphere(radius=15.0, theta_resolution=40, phi_resolution=42)
    rng = np.random.default_rng(7)
    vertices = np.asarray(sphere.points, float) + rng.normal(0.0, 0.04, (sphere.n_points, 3))
    return vertices, sphere.faces.reshape(-1, 4)[:, 1:]


def test_closest_points_are_open3ds(bumpy_sphere):
    vertices, triangles = bumpy_sphere
    rng = np.random.default_rng(1)
    direction = rng.normal(size=(20000, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    radius = np.concatenate([15.0 + rng.normal(0.0, 0.3, 15000), rng.uniform(0.0, 40.0, 5000)])
    points = direction * radius[:, None]
    ours = TriangleBVH(vertices, triangles).closest(points)
    theirs = TriangleScene(vertices, triangles).closest(points)
    gap = ours.distance_mm - theirs.distance_mm
    # never farther than open3d's point (beyond its float32 rounding), and the same distance
    # but for open3d's rounding (~1e-6 mm at 15 mm)
    assert gap.max() < 1e-5, gap.max()
    assert np.quantile(np.abs(gap), 0.99) < 1e-5
    near = np.abs(radius - 15.0) < 1.0
    assert np.abs(ours.points - theirs.points)[near].max() < 1e-3
    # the point is where its triangle's corners, weighted, put it, and at the stated distance
    assert np.allclose(np.einsum("nij,ni->nj", vertices[ours.nodes], ours.weights), ours.points,
                       atol=1e-9)
    assert np.allclose(np.linalg.norm(points - ours.points, axis=1), ours.distance_mm)
    assert (ours.weights >= 0).all() and np.allclose(ours.weights.sum(axis=1), 1.0)


def test_ray_hits_are_open3ds(bumpy_sphere):
    vertices, triangles = bumpy_sphere
    rng = np.random.default_rng(2)
    n = 20000
    camera = np.array([0.0, 0.0, -200.0])  # rays from a camera through the sphere and past it
    target = np.column_stack([rng.uniform(-18, 18, n), rng.uniform(-18, 18, n), np.zeros(n)])
    dirs = target - camera
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    # and rays from inside, outwards (their first hit is the far side's inner face)
    inside = rng.normal(0.0, 3.0, (5000, 3))
    out = rng.normal(size=(5000, 3))
    origins = np.vstack([np.broadcast_to(camera, (n, 3)), inside])
    dirs = np.vstack([dirs, out / np.linalg.norm(out, axis=1, keepdims=True)])
    ours = TriangleBVH(vertices, triangles).cast(origins, dirs)
    theirs = TriangleScene(vertices, triangles).cast(origins, dirs)
    hit = np.isfinite(ours["t_hit"])
    assert (hit == np.isfinite(theirs["t_hit"])).all()
    assert 0.4 * n < hit[:n].sum() < 0.95 * n and hit[n:].all()
    # open3d's float32 at 200 mm: a few 1e-5 mm; ours within 3 ppm of the distance
    t = ours["t_hit"][hit]
    assert (np.abs(t - theirs["t_hit"][hit]) < 3e-6 * t + 1e-5).all()
    same = ours["primitive_ids"][hit] == theirs["primitive_ids"][hit].astype(np.int64)
    assert same.mean() > 0.999  # others: a ray through an edge, either triangle
    assert np.allclose(ours["primitive_uvs"][hit][same], theirs["primitive_uvs"][hit][same],
                       atol=1e-4)
    assert np.allclose(ours["primitive_normals"][hit][same],
                       theirs["primitive_normals"][hit][same], atol=1e-4)
    # the hit point, from the triangle and weights, is on the ray at t
    corners = vertices[triangles[ours["primitive_ids"][hit]]]
    uv = ours["primitive_uvs"][hit]
    w = np.column_stack([1 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]])
    on_ray = origins[hit] + ours["t_hit"][hit][:, None] * dirs[hit]
    assert np.allclose(np.einsum("nij,ni->nj", corners, w), on_ray, atol=1e-9)
    assert (ours["primitive_ids"][~hit] == -1).all()
    assert (ours["primitive_normals"][~hit] == 0).all()


def test_degenerate_triangles_and_empty_queries(bumpy_sphere):
    """Zero-area triangles (a repeated corner, three corners on a line) give no answer of
    their own and do not spoil their neighbours' (they are never the closest by NaN); no
    points, no rays: empty answers."""
    vertices, triangles = bumpy_sphere
    n = len(vertices)
    extra = np.array([[0.0, 0.0, 15.5], [1.0, 0.0, 15.5], [2.0, 0.0, 15.5]])
    vertices = np.vstack([vertices, extra])
    triangles = np.vstack([triangles, [[n, n + 1, n + 2], [n, n, n + 1], [n + 2, n + 2, n + 2]]])
    rng = np.random.default_rng(3)
    points = np.vstack([rng.normal(0.0, 0.2, (2000, 3)) + [1.0, 0.0, 15.4],
                        rng.normal(size=(2000, 3)) * 15.0])
    ours = TriangleBVH(vertices, triangles).closest(points)
    theirs = TriangleScene(vertices, triangles).closest(points)
    assert np.isfinite(ours.distance_mm).all()
    assert (ours.distance_mm - theirs.distance_mm).max() < 1e-5
    assert np.quantile(np.abs(ours.distance_mm - theirs.distance_mm), 0.99) < 1e-5
    scene = TriangleBVH(vertices, triangles)
    assert len(scene.closest(np.zeros((0, 3))).distance_mm) == 0
    assert len(scene.cast(np.zeros((0, 3)), np.zeros((0, 3)))["t_hit"]) == 0


def test_scan_queries_leave_open3d_unloaded():
    """The two queries load no open3d (what took it out of the scan process)."""
    import subprocess
    import sys

    code = ("import sys, numpy as np\n"
            "from dotshell.geometry.bvh import TriangleBVH\n"
            "v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])\n"
            "t = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])\n"
            "s = TriangleBVH(v, t)\n"
            "d = s.closest(np.array([[0.2, 0.2, -1.0]])).distance_mm[0]\n"
            "h = s.cast(np.array([[0.2, 0.2, -1.0]]), np.array([[0, 0, 1.0]]))['t_hit'][0]\n"
            "print(d, h, 'open3d' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split()
    assert float(out[0]) == pytest.approx(1.0) and float(out[1]) == pytest.approx(1.0)
    assert out[2] == "False"
