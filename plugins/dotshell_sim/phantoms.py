"""Procedural phantoms for the simulator, like the paper's Figs. 8–9: a mouse-like phantom lying
on the stage and a gummy-bear-like body standing on it.

Each is a smooth union of ellipsoids (approximate signed distances, polynomial smooth minimum),
cut flat at the plate (z ≥ 0, the side it stands on), sampled on a 0.2 mm grid and turned into
a closed triangle mesh by marching cubes (VTK flying edges through pyvista). The mesh *is* the
phantom's true geometry: it is ray-cast by :class:`dotshell_sim.scene.MeshShape`, and its
enclosed volume is the truth meshing results are compared with. Lengths in mm, sample frame
(z up from the plate, the turntable axis through x = y = 0).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

#: (centre (x, y, z), semi-axes (a, b, c)) of each part, mm
MOUSE_PARTS = (
    ((-2.0, 0.0, 5.0), (9.0, 5.5, 5.0)),     # body
    ((-8.5, 0.0, 4.5), (4.5, 5.0, 4.5)),     # haunches
    ((8.0, 0.0, 5.0), (4.5, 3.6, 3.6)),      # head
    ((12.0, 0.0, 4.3), (2.2, 1.8, 1.8)),     # snout
    ((7.0, 3.0, 8.3), (1.0, 2.2, 2.2)),      # right ear
    ((7.0, -3.0, 8.3), (1.0, 2.2, 2.2)),     # left ear
    ((5.0, 3.6, 1.2), (1.8, 1.2, 1.2)),      # front paws
    ((5.0, -3.6, 1.2), (1.8, 1.2, 1.2)),
    ((-8.0, 4.2, 1.4), (3.0, 1.6, 1.4)),     # hind paws
    ((-8.0, -4.2, 1.4), (3.0, 1.6, 1.4)),
)
GUMMY_BEAR_PARTS = (
    ((0.0, 0.0, 6.5), (4.6, 3.6, 5.2)),      # belly
    ((0.0, 0.0, 14.0), (4.3, 3.4, 3.8)),     # head
    ((0.0, -1.6, 13.4), (1.8, 1.6, 1.4)),    # muzzle (camera side at 0° is +x; turns anyway)
    ((3.2, 0.0, 17.0), (1.3, 1.1, 1.3)),     # ears
    ((-3.2, 0.0, 17.0), (1.3, 1.1, 1.3)),
    ((4.4, -0.6, 8.6), (1.6, 1.6, 2.6)),     # arms
    ((-4.4, -0.6, 8.6), (1.6, 1.6, 2.6)),
    ((2.4, -0.8, 1.6), (2.0, 2.4, 2.2)),     # feet
    ((-2.4, -0.8, 1.6), (2.0, 2.4, 2.2)),
)
PHANTOMS = {"mouse": (MOUSE_PARTS, 1.2), "gummy-bear": (GUMMY_BEAR_PARTS, 0.9)}
GRID_MM = 0.2


def _ellipsoid_distance(p: np.ndarray, centre, axes) -> np.ndarray:
    """Approximate signed distance to an ellipsoid (exact on the surface, mm)."""
    q = (p - np.asarray(centre)) / np.asarray(axes)
    k0 = np.linalg.norm(q, axis=-1)
    k1 = np.linalg.norm(q / np.asarray(axes), axis=-1)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)


def _smooth_min(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def phantom_distance(points: np.ndarray, kind: str) -> np.ndarray:
    """Approximate signed distance (mm, negative inside) of the phantom, cut at z = 0."""
    parts, blend = PHANTOMS[kind]
    d = None
    for centre, axes in parts:
        e = _ellipsoid_distance(points, centre, axes)
        d = e if d is None else _smooth_min(d, e, blend)
    return np.maximum(d, -points[..., 2])


@lru_cache(maxsize=4)
def phantom_mesh(kind: str) -> tuple[np.ndarray, np.ndarray]:
    """Closed triangle mesh (vertices (V, 3) mm, outward triangles (F, 3)) of a phantom."""
    import pyvista as pv

    if kind not in PHANTOMS:
        raise ValueError(f"unknown phantom {kind!r}; choose one of {', '.join(PHANTOMS)}")
    parts, _ = PHANTOMS[kind]
    lo = np.min([np.subtract(c, a) for c, a in parts], axis=0) - 1.0
    hi = np.max([np.add(c, a) for c, a in parts], axis=0) + 1.0
    lo[2] = -1.0
    dims = np.ceil((hi - lo) / GRID_MM).astype(int) + 1
    grid = pv.ImageData(dimensions=tuple(dims), spacing=(GRID_MM,) * 3, origin=tuple(lo))
    grid.point_data["d"] = phantom_distance(np.asarray(grid.points), kind)
    surf = grid.contour([0.0], scalars="d", method="flying_edges").triangulate().clean()
    tri = surf.faces.reshape(-1, 4)[:, 1:].astype(np.int64)
    verts = np.asarray(surf.points, np.float64)
    v = verts[tri]
    if np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() < 0:
        tri = tri[:, ::-1]
    return verts, tri


def phantom_volume_mm3(kind: str) -> float:
    """Enclosed volume of the phantom's mesh (the truth for meshing checks)."""
    verts, tri = phantom_mesh(kind)
    v = verts[tri]
    return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)


def gummy_material(material_cls):
    """The ``gummy`` material: gelatine–sugar body, glossy, strongly forward-scattering and
    weakly absorbing (μs' ≈ 0.6/mm, μa ≈ 0.02/mm, n ≈ 1.45) when the simulator has its
    subsurface model (:mod:`dotshell_sim.subsurface`); an opaque, glossy stand-in otherwise."""
    try:
        from dotshell_sim.subsurface import Scattering
    except ImportError:
        return material_cls("gummy", albedo=0.55, specular=0.05, shininess=200.0)
    return material_cls("gummy", albedo=0.03, specular=0.04, shininess=300.0,
                        depolarization=0.0,
                        scattering=Scattering(mus_prime_per_mm=0.6, mua_per_mm=0.02, n=1.45))
