"""How one camera view sees the nodes of a closed surface mesh, and the light each node sends
to the camera.

Geometry (:func:`view_surface`), per view, in the camera frame (mm):

* node normals: area-weighted vertex normals of the outward-oriented surface;
* per node, the unit view vector from the node to the camera centre (not the optical axis) and
  ``sin β`` = normal · view vector, the paper's Eq. 1 orientation term;
* every camera pixel inside the surface's image is ray-cast against the mesh
  (:class:`dotshell.geometry.bvh.TriangleBVH`); its first hit gives the triangle, barycentric
  weights (each node's linear "hat" function there), the distance and the cosine between the
  ray and the face normal;
* node masks, first reason wins: ``outside_image`` (projects outside the frame or behind the
  camera), ``facing_away`` (sin β ≤ 0), ``occluded`` (the ray from the camera centre to the node
  hits the surface first), ``grazing`` (sin β below the limit), ``crease`` (the surface turns
  more than the limit within the node's star, :func:`normal_spread_deg`: a sharp edge or a
  feature smaller than the node spacing, so the node has no single orientation),
  ``unscanned`` (the caller's flag for nodes the scan did not measure, e.g. where the mesher
  closed the bottom: their orientation is a guess).

Light (:func:`node_intensities`), per image: the **node intensity** is the power the node's
surface element sends towards the camera per unit of its area, from the pixels it covers::

    I_k = Σ_p w_kp · v_p · a⊥_p  /  Σ_p w_kp · a⊥_p / cos θ_p

with ``v_p`` the pixel value (∝ radiance), ``w_kp`` the node's hat weight in pixel p,
``a⊥_p = t_p² · ω_p`` the pixel footprint perpendicular to its ray (ω_p its solid angle, t_p the
distance) and ``a⊥_p / cos θ_p`` the footprint on the surface. For a surface of uniform radiance
L this is ``L · sin β``, the paper's ``I_k = I0_k · sin β_k`` for a Lambertian emitter. Nodes
covering fewer than ``min_pixels`` hat-weighted pixels are ``unsampled``; nodes touching a
saturated pixel are ``saturated``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dotshell.fem.meshes import TriangleSurface, enclosed_volume_mm3
from dotshell.geometry.calibration import RigCalibration
from dotshell.geometry.bvh import TriangleBVH
from dotshell.geometry.raycast import barycentric_weights

#: node mask reasons, in the order they are decided (code = index)
MASK_REASONS = ("ok", "outside_image", "facing_away", "occluded", "grazing", "crease",
                "unscanned", "unsampled", "saturated")
OK, OUTSIDE, FACING_AWAY, OCCLUDED, GRAZING, CREASE, UNSCANNED, UNSAMPLED, SATURATED = \
    range(len(MASK_REASONS))


@dataclass
class SurfaceView:
    """One view of a surface. Node arrays have one entry per surface vertex; pixel arrays one
    per camera pixel whose ray hits the surface (front faces only)."""

    angle_deg: float
    image_size: tuple[int, int]       # (width, height) px
    nodes_cam: np.ndarray             # (N, 3) mm, camera frame
    normals_cam: np.ndarray           # (N, 3) unit outward normals, camera frame
    sin_beta: np.ndarray              # (N,) cosine between normal and node → camera centre
    node_px: np.ndarray               # (N, 2) distorted pixel coordinates (NaN behind camera)
    mask: np.ndarray                  # (N,) int8 geometric mask code (MASK_REASONS)
    pixel_index: np.ndarray           # (M,) flat index row * width + col
    pixel_nodes: np.ndarray           # (M, 3) node indices of the hit triangle
    pixel_weights: np.ndarray         # (M, 3) barycentric (hat) weights
    pixel_area_perp: np.ndarray       # (M,) mm², footprint perpendicular to the ray
    pixel_cos: np.ndarray             # (M,) cos between ray and face normal (> 0)


def _outward_face_vectors(surface: TriangleSurface) -> np.ndarray:
    """Per triangle, its normal scaled by twice its area, pointing out of the enclosed volume."""
    v, t = surface.vertices, surface.triangles
    face = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    return -face if enclosed_volume_mm3(surface) < 0 else face


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)


def vertex_normals(surface: TriangleSurface, faces: np.ndarray | None = None) -> np.ndarray:
    """Area-weighted unit vertex normals, pointing out of the enclosed volume (``faces``: the
    surface's :func:`_outward_face_vectors`, if already computed)."""
    face = _outward_face_vectors(surface) if faces is None else faces
    n = np.zeros_like(surface.vertices)
    for k in range(3):
        np.add.at(n, surface.triangles[:, k], face)
    return _unit(n)


def normal_spread_deg(surface: TriangleSurface) -> np.ndarray:
    """Per node, the largest angle (degrees) between its vertex normal and the normal of any
    triangle around it: how much the surface turns within the node's star. Large at sharp
    edges and on features smaller than the node spacing, where the node's orientation is
    uncertain."""
    t = surface.triangles
    faces = _outward_face_vectors(surface)
    normals = vertex_normals(surface, faces)
    face = _unit(faces)
    worst = np.ones(len(surface.vertices))
    for k in range(3):
        np.minimum.at(worst, t[:, k], np.einsum("ij,ij->i", face, normals[t[:, k]]))
    return np.degrees(np.arccos(np.clip(worst, -1.0, 1.0)))


def view_surface(surface: TriangleSurface, calib: RigCalibration, angle_deg: float,
                 min_sin_beta: float, unscanned: np.ndarray | None = None,
                 crease: np.ndarray | None = None) -> SurfaceView:
    """Project a sample-frame surface into the camera with the stage at ``angle_deg``;
    ``unscanned`` and ``crease`` (bool per node, view-independent) mark nodes not backed by
    measured points and nodes without a single orientation."""
    lens = calib.camera
    width, height = lens.size
    nodes = calib.sample_to_camera(surface.vertices, angle_deg)
    normals = vertex_normals(surface) @ calib.sample_rotation(angle_deg).T
    dist = np.linalg.norm(nodes, axis=1)
    to_cam = -nodes / np.maximum(dist, 1e-12)[:, None]
    sin_beta = np.einsum("ij,ij->i", normals, to_cam)
    in_front = nodes[:, 2] > 1e-6
    px = np.full((len(nodes), 2), np.nan)
    px[in_front] = lens.project(nodes[in_front])
    inside = in_front & (px[:, 0] >= -0.5) & (px[:, 0] <= width - 0.5) \
        & (px[:, 1] >= -0.5) & (px[:, 1] <= height - 0.5)
    scene = TriangleBVH(nodes, surface.triangles)
    hit = scene.cast(np.zeros_like(nodes), -to_cam)
    tol = np.maximum(0.02, 1e-4 * dist)
    occluded = hit["t_hit"] < dist - tol
    mask = np.full(len(nodes), OK, np.int8)
    for code, flag in ((UNSCANNED, unscanned), (CREASE, crease)):
        if flag is not None:
            mask[flag] = code
    for code, bad in ((GRAZING, sin_beta < min_sin_beta), (OCCLUDED, occluded),
                      (FACING_AWAY, sin_beta <= 0), (OUTSIDE, ~inside)):
        mask[bad] = code  # later assignments win: outside > facing away > occluded > grazing
    pixels = _pixel_hits(scene, lens, px[inside])
    return SurfaceView(angle_deg, (width, height), nodes, normals, sin_beta, px, mask, *pixels)


def _pixel_hits(scene: TriangleBVH, lens, node_px: np.ndarray):
    width, height = lens.size
    if len(node_px) == 0:
        e = np.zeros(0)
        return e.astype(np.int64), np.zeros((0, 3), np.int64), np.zeros((0, 3)), e, e
    lo = np.clip(np.floor(node_px.min(axis=0)).astype(int) - 2, 0, None)
    hi = np.minimum(np.ceil(node_px.max(axis=0)).astype(int) + 2, [width - 1, height - 1])
    cols, rows = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1))
    pix = np.column_stack([cols.ravel(), rows.ravel()]).astype(float)
    dirs = lens.rays(pix)
    hit = scene.cast(np.zeros_like(dirs), dirs)
    cos = -np.einsum("ij,ij->i", hit["primitive_normals"].astype(float), dirs)
    ok = np.isfinite(hit["t_hit"]) & (cos > 1e-3)  # front faces only
    K = lens.K
    t = hit["t_hit"][ok].astype(float)
    solid_angle = dirs[ok, 2] ** 3 / (K[0, 0] * K[1, 1])  # pinhole pixel solid angle, sr
    weights = barycentric_weights(hit["primitive_uvs"][ok])
    index = (rows.ravel()[ok] * width + cols.ravel()[ok]).astype(np.int64)
    tri = scene.triangles[hit["primitive_ids"][ok].astype(np.int64)]
    return index, tri, weights, t * t * solid_angle, cos[ok]


@dataclass
class NodeLight:
    """Per-node light of one image over a :class:`SurfaceView`."""

    intensity: np.ndarray     # (N,) power towards the camera per unit surface area (image units)
    radiance: np.ndarray      # (N,) hat-weighted mean pixel value
    pixels: np.ndarray        # (N,) hat-weighted pixel count
    mask: np.ndarray          # (N,) int8 final mask code


def node_intensities(view: SurfaceView, image: np.ndarray, saturated: np.ndarray,
                     min_pixels: float) -> NodeLight:
    """Node intensities from ``image`` (float, flat-fielded, dark-subtracted); ``saturated`` a
    bool image of clipped pixels. NaN where the node is masked."""
    n = len(view.sin_beta)
    v = image.ravel()[view.pixel_index]
    sat = saturated.ravel()[view.pixel_index]
    nodes, w = view.pixel_nodes.ravel(), view.pixel_weights.ravel()
    power = np.bincount(nodes, w * np.repeat(v * view.pixel_area_perp, 3), n)
    area = np.bincount(nodes, w * np.repeat(view.pixel_area_perp / view.pixel_cos, 3), n)
    count = np.bincount(nodes, w, n)
    value = np.bincount(nodes, w * np.repeat(v, 3), n)
    touched_sat = np.bincount(nodes, w * np.repeat(sat.astype(float), 3), n) > 0.05
    mask = view.mask.copy()
    ok = mask == OK
    mask[ok & (count < max(min_pixels, 1e-9))] = UNSAMPLED
    mask[(mask == OK) & touched_sat] = SATURATED
    good = mask == OK
    with np.errstate(invalid="ignore", divide="ignore"):
        intensity = np.where(good, power / area, np.nan)
        radiance = np.where(good, value / count, np.nan)
    return NodeLight(intensity, radiance, count, mask)


def mask_counts(mask: np.ndarray) -> dict[str, int]:
    """Nodes per mask reason (every reason listed, zeros included)."""
    counts = np.bincount(mask.astype(np.int64), minlength=len(MASK_REASONS))
    return {r: int(c) for r, c in zip(MASK_REASONS, counts)}


def resample_to_image(view: SurfaceView, node_values: np.ndarray) -> np.ndarray:
    """Float32 image (H, W) of per-node values interpolated with the hat weights at every pixel
    that sees the surface; NaN elsewhere and where a corner node has no value."""
    width, height = view.image_size
    out = np.full(width * height, np.nan, np.float32)
    vals = node_values[view.pixel_nodes]
    out[view.pixel_index] = np.einsum("ij,ij->i", vals, view.pixel_weights)
    return out.reshape(height, width)
