"""Surface mesher ``open3d-poisson``: merged point cloud → closed, outward-oriented triangle
surface with about the requested node distance.

Steps (all lengths mm):

1. statistical outlier removal (open3d; dense clouds are first thinned to a third of the
   voxel), then voxel down-sampling;
2. the open bottom (the region of interest drops points near the stage plate) is closed at the
   plate plane ``bottom_z_mm``: the lowest band of the cloud is extended straight down to the
   plane and the footprint it encloses is filled with points whose normals point down;
3. normals estimated from neighbourhoods and turned towards the sensor that saw each point
   (outward on a solid), or away from the centroid when no viewpoints are known;
4. screened Poisson reconstruction, vertices of low Poisson density trimmed (the surface the
   reconstruction invents far from any data);
5. uniform remeshing to the target node distance (ACVD Voronoi clustering, ``pyacvd``);
6. repair to a closed 2-manifold (``pymeshfix``: holes filled, self-intersections and
   degenerate faces removed) and a final check.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from dotshell.runtime.compat import import_open3d
from dotshell.runtime.process import heap_reused
from dotshell.geometry.raycast import TriangleScene
from dotshell.fem.meshes import (MeshError, SurfaceResult, TriangleSurface, closed_manifold_problems,
                          enclosed_volume_mm3, triangle_areas_mm2)
from dotshell.settings import Setting

SETTINGS: dict[str, Setting] = {
    "outlier_neighbors": Setting("int", 20, "neighbours in the statistical outlier filter",
                                 min=2),
    "outlier_std_ratio": Setting("float", 2.0, "drop points whose mean neighbour distance is "
                                 "above mean + ratio × std", min=0.1),
    "voxel_mm": Setting("float", 0.0, "down-sampling voxel; 0 = half the node distance, at "
                        "least 0.1 mm", "mm", min=0.0),
    "poisson_depth": Setting("int", 0, "octree depth of the Poisson reconstruction; 0 = "
                             "automatic (cells of about one voxel)", min=0, max=12),
    "density_quantile": Setting("float", 0.02, "trim Poisson vertices whose density is below "
                                "this quantile", min=0.0, max=0.5),
    "min_points": Setting("int", 500, "fewest cloud points (after filtering) a surface is "
                          "attempted from", min=10),
}


class PoissonSurfaceMesher:
    """Implements :class:`dotshell.fem.meshes.SurfaceMesher` with open3d, pyacvd and pymeshfix."""

    def __init__(self, settings: dict[str, Any]):
        self.s = settings

    def surface(self, points_mm: np.ndarray, viewpoints_mm: np.ndarray | None,
                node_distance_mm: float, bottom_z_mm: float | None) -> SurfaceResult:
        check_node_distance(node_distance_mm)
        o3d = import_open3d()
        stats: dict[str, Any] = {"input_points": int(len(points_mm))}
        t0 = time.perf_counter()
        voxel = self.s["voxel_mm"] or default_voxel_mm(node_distance_mm)
        pcd = _thinned_cloud(o3d, points_mm, viewpoints_mm, voxel / 3)
        pcd, _ = pcd.remove_statistical_outlier(self.s["outlier_neighbors"],
                                                self.s["outlier_std_ratio"])
        pcd = pcd.voxel_down_sample(voxel)
        stats["filtered_points"] = len(pcd.points)
        self._require_points(len(pcd.points), len(points_mm), voxel)
        pts = np.asarray(pcd.points)
        _require_not_flat(pts, max(node_distance_mm / 2, 2 * voxel))
        views = np.asarray(pcd.normals).copy() if viewpoints_mm is not None else None
        normals = _oriented_normals(o3d, pts, views, voxel)
        if bottom_z_mm is not None:
            pts, normals, n_added = close_bottom(pts, normals, bottom_z_mm, voxel)
            stats["bottom_points_added"] = n_added
        stats["seconds_filter"] = round(time.perf_counter() - t0, 3)
        t0 = time.perf_counter()
        dense = repair_closed(self._poisson(o3d, pts, normals, voxel, stats), "Poisson surface")
        if bottom_z_mm is not None:
            dense = cut_and_cap(dense, bottom_z_mm)
        stats["seconds_poisson"] = round(time.perf_counter() - t0, 3)
        t0 = time.perf_counter()
        surf = remesh_uniform(dense, node_distance_mm)
        surf = repair_closed(surf, "remeshed surface")
        stats["seconds_remesh_repair"] = round(time.perf_counter() - t0, 3)
        stats.update(surface_stats(surf))
        _require_solid(stats, node_distance_mm)
        return SurfaceResult(surf, stats)

    def _require_points(self, n: int, n_in: int, voxel: float) -> None:
        if n < self.s["min_points"]:
            raise MeshError(
                f"the cloud is too sparse to close a surface: {n} points remain of {n_in} after "
                f"outlier removal and {voxel:.2f} mm voxels (at least {self.s['min_points']} "
                "needed). Scan more views or at a higher resolution, or lower "
                "[surface_mesher.settings] min_points / voxel_mm.")

    def _poisson(self, o3d, pts: np.ndarray, normals: np.ndarray, voxel: float,
                 stats: dict[str, Any]) -> TriangleSurface:
        extent = float(np.ptp(pts, axis=0).max()) * 1.1
        depth = self.s["poisson_depth"] or int(np.clip(math.ceil(math.log2(extent / voxel)), 5, 10))
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        pcd.normals = o3d.utility.Vector3dVector(normals)
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            # one thread: open3d's multi-threaded Poisson solve differs from run to run in
            # the last bits, so meshes of the same cloud would not be the same bytes
            mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
                pcd, depth=depth, scale=1.1, linear_fit=False, n_threads=1)
        density = np.asarray(density)
        if len(density) == 0:
            raise MeshError("Poisson reconstruction produced no surface from the cloud; it is "
                            "too sparse or too flat to enclose a volume.")
        cut = np.quantile(density, self.s["density_quantile"])
        mesh.remove_vertices_by_mask(density < cut)
        stats["poisson_depth"] = depth
        stats["poisson_vertices"] = len(mesh.vertices)
        return TriangleSurface(np.asarray(mesh.vertices), np.asarray(mesh.triangles))


def _require_not_flat(pts: np.ndarray, min_thickness_mm: float) -> None:
    """Refuse a cloud that is a sheet (2nd–98th percentile spread along its thinnest principal
    axis below ``min_thickness_mm``): it cannot enclose a volume, whatever Poisson makes of it."""
    centred = pts - pts.mean(axis=0)
    _, _, axes = np.linalg.svd(centred[:: max(1, len(pts) // 50_000)], full_matrices=False)
    lo, hi = np.percentile(centred @ axes[2], [2, 98])
    if hi - lo < min_thickness_mm:
        raise MeshError(
            f"the cloud is a sheet {hi - lo:.3f} mm thick (at least {min_thickness_mm:.2f} mm "
            "needed to enclose a volume): it covers only one side of the sample. Scan all around "
            "it (more views) or check [processing.roi].")


def _require_solid(stats: dict[str, Any], node_distance_mm: float) -> None:
    """Refuse a closed surface that encloses (almost) nothing: a sheet closed onto itself."""
    thickness = 3.0 * stats["enclosed_volume_mm3"] / max(stats["area_mm2"], 1e-12)
    if thickness < node_distance_mm / 4:
        raise MeshError(
            f"the closed surface encloses almost no volume ({stats['enclosed_volume_mm3']:.2f} "
            f"mm³ for {stats['area_mm2']:.1f} mm², mean thickness {thickness:.3f} mm): the cloud "
            "covers only one side of the sample. Scan all around it (more views) or check "
            "[processing.roi].")


def default_voxel_mm(node_distance_mm: float) -> float:
    """The down-sampling voxel when ``voxel_mm`` is 0: half the node distance, at least 0.1 mm.

    The surface is remeshed to edges of the node distance, so detail finer than half of it
    is lost anyway; a quarter (before issue 33) gave 3.6x the points, a Poisson octree one
    level deeper and a 4x larger surface to repair, for the same mesh (metal cylinder at 1 mm:
    volume error -0.426 vs -0.423 %, side radius within 0.001 mm; benchmarks/mesh_bench.py)."""
    return max(0.1, node_distance_mm / 2)


def check_node_distance(node_distance_mm: float) -> None:
    if not (isinstance(node_distance_mm, (int, float)) and math.isfinite(node_distance_mm)
            and node_distance_mm > 0):
        raise MeshError(f"node distance must be a positive number of mm, got "
                        f"{node_distance_mm!r}. Set [mesh] node_distance_mm (e.g. 1.0) or pass "
                        "--node-distance.")


#: Points thinned at a time (millions of points: open3d's copies of the whole cloud and its
#: viewpoints took ~1 GB at full resolution; a chunk at a time, tens of MB).
THIN_CHUNK = 250_000


def _thinned_cloud(o3d, points_mm: np.ndarray, viewpoints_mm: np.ndarray | None,
                   voxel_mm: float):
    """The finite points (with their viewpoints as normals, carried through the filters) as an
    open3d cloud; above 200,000 points first thinned to ``voxel_mm`` voxels, a chunk of
    :data:`THIN_CHUNK` points at a time (the outlier filter is O(N k))."""
    n = len(points_mm)
    parts = []
    # each chunk's float64 copies, viewpoints and open3d's copies of them are ~30 MB allocated
    # and freed again: from the heap, reused, rather than new pages each time
    with heap_reused():
        for s in range(0, n, THIN_CHUNK if n > 200_000 else max(n, 1)):
            pts, views = _finite(points_mm[s:s + THIN_CHUNK], None if viewpoints_mm is None
                                 else viewpoints_mm[s:s + THIN_CHUNK])
            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
            if views is not None:
                pcd.normals = o3d.utility.Vector3dVector(views)
            parts.append(pcd.voxel_down_sample(voxel_mm) if n > 200_000 else pcd)
        pts = views = pcd = None  # the last chunk's arrays go before the heap is trimmed
    if len(parts) <= 1:
        return parts[0] if parts else o3d.geometry.PointCloud()
    out = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(
        np.concatenate([np.asarray(p.points) for p in parts])))
    if viewpoints_mm is not None:
        out.normals = o3d.utility.Vector3dVector(
            np.concatenate([np.asarray(p.normals) for p in parts]))
    return out.voxel_down_sample(voxel_mm)  # a voxel seen by several chunks: one point again


def _finite(points: np.ndarray, views: np.ndarray | None):
    """The rows of ``points`` (and ``views``) that are finite, as float64; the arrays
    themselves when every row is (no copies: at 5.5 M points each was 133 MB)."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    if views is not None:
        views = np.asarray(views, np.float64).reshape(-1, 3)
    if np.isfinite(pts).all() and (views is None or np.isfinite(views).all()):
        return pts, views  # the usual case, found without the row-wise reduction
    ok = np.isfinite(pts).all(axis=1)
    if views is not None:
        ok &= np.isfinite(views).all(axis=1)
    return pts[ok], (None if views is None else views[ok])


def _oriented_normals(o3d, pts: np.ndarray, views: np.ndarray | None,
                      voxel: float) -> np.ndarray:
    """Unit normals turned towards each point's viewpoint (or away from the centroid)."""
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * voxel, max_nn=30))
    n = np.asarray(pcd.normals).copy()
    towards = (views - pts) if views is not None else (pts - pts.mean(axis=0))
    flip = np.einsum("ij,ij->i", n, towards) < 0
    n[flip] *= -1
    return n


def close_bottom(pts: np.ndarray, normals: np.ndarray, bottom_z_mm: float,
                 spacing_mm: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Extend the lowest band of the cloud down to ``bottom_z_mm`` and fill the footprint it
    encloses with downward-facing points ``spacing_mm`` apart. Returns points, normals and the
    number added."""
    z0 = float(pts[:, 2].min())
    band = pts[:, 2] <= z0 + 3 * spacing_mm
    if z0 < bottom_z_mm - spacing_mm or band.sum() < 3:
        return pts, normals, 0
    ring, ring_n = pts[band], normals[band].copy()
    ring_n[:, 2] = 0.0  # walls: keep the horizontal part of the normal
    nn = np.linalg.norm(ring_n, axis=1, keepdims=True)
    ring_n = np.where(nn > 1e-6, ring_n / np.maximum(nn, 1e-12), 0.0)
    walls = []
    steps = np.arange(bottom_z_mm, z0, spacing_mm)
    for z in steps:
        w = ring.copy()
        w[:, 2] = z
        walls.append(w)
    wall_pts = np.concatenate(walls) if walls else np.empty((0, 3))
    wall_n = np.tile(ring_n, (len(walls), 1)) if walls else np.empty((0, 3))
    floor = _footprint_points(ring[:, :2], bottom_z_mm, spacing_mm)
    floor_n = np.tile([0.0, 0.0, -1.0], (len(floor), 1))
    add_p = np.concatenate([wall_pts, floor])
    add_n = np.concatenate([wall_n, floor_n])
    return np.concatenate([pts, add_p]), np.concatenate([normals, add_n]), len(add_p)


def _footprint_points(xy: np.ndarray, z: float, spacing: float) -> np.ndarray:
    """Grid points (spacing apart) inside the outline traced by ``xy`` (filled raster)."""
    lo = xy.min(axis=0) - 2 * spacing
    ij = np.floor((xy - lo) / spacing).astype(int)
    shape = ij.max(axis=0) + 3
    mask = np.zeros(shape, bool)
    mask[ij[:, 0], ij[:, 1]] = True
    mask = fill_holes(closing(mask, iterations=2))
    ii, jj = np.nonzero(mask)
    centre = lo + (np.column_stack([ii, jj]) + 0.5) * spacing
    return np.column_stack([centre, np.full(len(centre), z)])


# The footprint's closing and hole filling were scipy.ndimage's (binary_closing with two
# iterations, binary_fill_holes, both with the 4-neighbour cross): importing scipy.ndimage
# cost the mesh process ~0.25 s of CPU for a raster of a few thousand cells. The same
# operations below give the same masks (tests/test_mesh.py compares them with scipy's).

def _dilated(mask: np.ndarray) -> np.ndarray:
    """``mask`` grown by one cell towards its 4 neighbours."""
    out = mask.copy()
    out[1:] |= mask[:-1]
    out[:-1] |= mask[1:]
    out[:, 1:] |= mask[:, :-1]
    out[:, :-1] |= mask[:, 1:]
    return out


def _eroded(mask: np.ndarray) -> np.ndarray:
    """``mask`` less every cell with a 4-neighbour outside it (outside the raster counts as
    outside the mask)."""
    out = mask.copy()
    out[1:] &= mask[:-1]
    out[:-1] &= mask[1:]
    out[:, 1:] &= mask[:, :-1]
    out[:, :-1] &= mask[:, 1:]
    out[[0, -1], :] = False
    out[:, [0, -1]] = False
    return out


def closing(mask: np.ndarray, iterations: int = 1) -> np.ndarray:
    """Morphological closing of a 2-D boolean raster with the 4-neighbour cross:
    ``iterations`` dilations, then as many erosions (scipy.ndimage.binary_closing's result)."""
    for _ in range(iterations):
        mask = _dilated(mask)
    for _ in range(iterations):
        mask = _eroded(mask)
    return mask


def fill_holes(mask: np.ndarray) -> np.ndarray:
    """``mask`` with the cells it encloses: every cell outside it that cannot reach the
    raster's edge through 4-neighbours outside it (scipy.ndimage.binary_fill_holes's result);
    OpenCV's flood fill from a margin around the raster."""
    import cv2

    padded = np.zeros((mask.shape[0] + 2, mask.shape[1] + 2), np.uint8)
    padded[1:-1, 1:-1] = mask
    cv2.floodFill(padded, None, (0, 0), 2, flags=4)
    return padded[1:-1, 1:-1] != 2


def cut_and_cap(surface: TriangleSurface, z_mm: float) -> TriangleSurface:
    """Cut a closed surface with the plane z = ``z_mm``, drop what is below and close the cut
    with a flat cap (VTK's closed-surface clipping)."""
    import pyvista as pv

    if surface.vertices[:, 2].min() >= z_mm:
        return surface
    faces = np.hstack([np.full((len(surface.triangles), 1), 3), surface.triangles]).ravel()
    poly = pv.PolyData(surface.vertices, faces)
    cut = poly.clip_closed_surface(normal=(0.0, 0.0, 1.0), origin=(0.0, 0.0, z_mm),
                                   tolerance=1e-6).triangulate().clean()
    if cut.n_cells == 0:
        raise MeshError(f"nothing of the surface lies above the plate plane z = {z_mm} mm; "
                        "check [mesh] bottom_z_mm and the cloud's height range.")
    return TriangleSurface(np.asarray(cut.points), cut.faces.reshape(-1, 4)[:, 1:])


def remesh_uniform(surface: TriangleSurface, node_distance_mm: float) -> TriangleSurface:
    """Uniform remeshing by ACVD clustering: vertex count = area / (√3/2 · d²), the area one
    vertex of an equilateral mesh with edge ``d`` owns."""
    import pyacvd
    import pyvista as pv

    area = float(triangle_areas_mm2(surface).sum())
    n_vertices = int(round(area / (math.sqrt(3) / 2 * node_distance_mm ** 2)))
    if n_vertices < 20:
        raise MeshError(f"node distance {node_distance_mm} mm is too coarse for a surface of "
                        f"{area:.1f} mm² (it would have {n_vertices} nodes); use at most "
                        f"{math.sqrt(area / (20 * math.sqrt(3) / 2)):.2f} mm.")
    faces = np.hstack([np.full((len(surface.triangles), 1), 3), surface.triangles]).ravel()
    poly = pv.PolyData(surface.vertices, faces).clean()
    # ACVD clusters input vertices: long triangles (a flat cap) must be split first
    poly = poly.subdivide_adaptive(max_edge_len=node_distance_mm / 3)
    clus = pyacvd.Clustering(poly)
    while clus.mesh.n_points < 3 * n_vertices:
        clus.subdivide(2)
    clus.cluster(n_vertices)
    # pyacvd's own move of the nodes onto the surface (moveclus) searches the 1000 nearest
    # triangles of every node (most of the remeshing time); the closest point of the surface
    # is found in a BVH instead
    out = clus.create_mesh(moveclus=False)
    dense = clus.mesh
    nodes = TriangleScene(dense.points, dense.faces.reshape(-1, 4)[:, 1:]).closest(out.points)
    return TriangleSurface(nodes.points, out.faces.reshape(-1, 4)[:, 1:])


def repair_closed(surface: TriangleSurface, what: str = "surface") -> TriangleSurface:
    """Close holes and remove self-intersections (pymeshfix); orient outward; verify."""
    import pymeshfix

    fix = pymeshfix.MeshFix(surface.vertices, surface.triangles.astype(np.int32))
    fix.repair(joincomp=False, remove_smallest_components=True)
    out = TriangleSurface(np.asarray(fix.points), np.asarray(fix.faces).reshape(-1, 3))
    if len(out.triangles) and enclosed_volume_mm3(out) < 0:
        out = TriangleSurface(out.vertices, out.triangles[:, ::-1])
    problems = closed_manifold_problems(out)
    if problems:
        raise MeshError(f"the {what} could not be repaired to a closed manifold ("
                        + "; ".join(problems) + "). The cloud probably misses whole sides of "
                        "the sample: scan more views, or check [processing.roi].")
    return out


def surface_stats(surface: TriangleSurface) -> dict[str, Any]:
    e = surface.triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    lengths = np.linalg.norm(surface.vertices[e[:, 0]] - surface.vertices[e[:, 1]], axis=1)
    return {
        "vertices": int(len(surface.vertices)),
        "triangles": int(len(surface.triangles)),
        "area_mm2": float(triangle_areas_mm2(surface).sum()),
        "enclosed_volume_mm3": enclosed_volume_mm3(surface),
        "edge_length_mm": {"mean": float(lengths.mean()), "min": float(lengths.min()),
                           "max": float(lengths.max())},
        "closed_manifold": not closed_manifold_problems(surface),
    }
