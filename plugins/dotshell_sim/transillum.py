"""Trans-illumination in the simulator: light from a laser spot on the sample's far side,
diffusing through the TRUE sample and leaving its surface towards the camera.

Model (docs/light-model.md, "Trans-illumination"; lengths mm, coefficients 1/mm):

1. **Volume**: the true sample (the analytic cylinder as a closed triangulated surface, a mesh
   phantom's marching-cubes surface decimated to the node spacing) is filled with tetrahedra by
   TetGen. The continuous-wave diffusion equation with NIRFAST's Robin boundary
   (:func:`dotshell.fem.forward.system_matrix`) is solved for a unit point source one transport
   length ``1/μs'`` inside the beam's entry point, along the beam: φ per node (1/mm² per unit
   power). The system matrix is symmetric positive definite; it is solved by conjugate
   gradients with a Jacobi preconditioner (:func:`dotshell.fem.forward.jacobi_cg`, to a relative
   residual of 1e-10), the solver of :func:`dotshell.fem.forward.solve_cw`.
2. **Surface**: φ at a surface point is read by snapping the point to the FEM boundary
   (:class:`dotshell.geometry.bvh.TriangleBVH`, closest point) and interpolating the
   boundary triangle's node values barycentrically.
3. **Exit**: the radiance leaving the surface towards the camera is
   ``P · φ · L(θo)/φ`` with :func:`dotshell.fem.optics.exit_radiance_per_fluence` (Fresnel
   transmission and the Robin flux term), θo the angle between the outward normal and the
   direction from the surface point to the camera centre. ``P`` is the beam power in the
   renderer's relative units (1 = the radiance of a white Lambertian surface under the
   projector's reference irradiance), so P·φ·L is directly comparable with projector light.

The beam is fixed in the stage frame: it comes from the far side (stage x < 0) and travels
along +x, towards the camera, at target (y, z) = (lateral, height above the plate); the sample
turns with the stage, so the entry point in the sample frame depends on the stage angle.
"""

from __future__ import annotations

import hashlib
import math
import weakref
from collections import OrderedDict
from dataclasses import dataclass, field

from typing import TYPE_CHECKING

import numpy as np

from dotshell.errors import DeviceError
from dotshell.fem.meshes import (MeshError, TetMesh, TriangleSurface, closed_manifold_problems,
                          compact, element_containing, orient_positive)
from dotshell.geometry.calibration import rot_z
from dotshell.geometry.lens import Lens
from dotshell.geometry.bvh import TriangleBVH
from dotshell.fem.optics import exit_radiance_per_fluence

from dotshell_sim.lru import cached
from dotshell_sim.render import Renderer, View, subpixel_grid
from dotshell_sim.scene import Cylinder, Material, MeshShape

if TYPE_CHECKING:  # scipy and the FEM solver load when a laser is first modelled: every
    import scipy.sparse as sp  # command that loads the plugins imported them (0.5-1 s)

#: Where the beam starts, stage frame x (mm): far behind any sample, before the background.
_BEAM_START_MM = -1000.0
#: Largest distance (mm) from the true surface at which the truth is reported.
MAX_SNAP_MM = 1.0


# ---- optical properties ------------------------------------------------------------------

@dataclass(frozen=True)
class Optics:
    """Homogeneous optical properties of the sample: μa, μs' (1/mm), refractive index n."""

    mua_per_mm: float
    musp_per_mm: float
    n: float

    @property
    def transport_length_mm(self) -> float:
        """1/μs': the depth below the entry point where the source is put (NIRFAST)."""
        return 1.0 / self.musp_per_mm


_SCENE_OPTICS_KEYS = ("mua_per_mm", "musp_per_mm")


def sample_optics(scene_settings: dict, material: Material, who: str = "sim-laser") -> Optics:
    """The sample's optics: the turbid material's scattering, else the scene's
    ``mua_per_mm`` / ``musp_per_mm`` / ``refractive_index`` keys.

    Raises:
        DeviceError: an opaque sample without optics keys, or keys on a turbid material.
    """
    given = {k: scene_settings.get(k) for k in _SCENE_OPTICS_KEYS}
    if material.scattering is not None:
        if any(v is not None for v in given.values()):
            sc = material.scattering
            raise DeviceError(
                f"{who}: [stage.settings.scene] mua_per_mm / musp_per_mm are for opaque-looking "
                f"samples, but material {material.name!r} is turbid and has its own optics "
                f"(μs' = {sc.mus_prime_per_mm}/mm, μa = {sc.mua_per_mm}/mm, n = {sc.n}); remove "
                "the keys or choose an opaque material.")
        sc = material.scattering
        return Optics(sc.mua_per_mm, sc.mus_prime_per_mm, sc.n)
    if any(v is None for v in given.values()):
        raise DeviceError(
            f"{who}: the sample ({scene_settings.get('kind')}, material {material.name!r}) is "
            "opaque and has no optical properties, so no light can pass through it. Set "
            "[stage.settings.scene] mua_per_mm and musp_per_mm (and refractive_index; e.g. "
            "0.01, 1.0 and 1.37 for soft tissue in the near infrared) or choose a turbid "
            "material such as \"agar\".")
    return Optics(float(given["mua_per_mm"]), float(given["musp_per_mm"]),
                  float(scene_settings.get("refractive_index") or 1.37))


# ---- the true sample as a closed surface and a tetrahedral mesh --------------------------

def cylinder_surface(radius_mm: float, height_mm: float, spacing_mm: float,
                     center_mm=(0.0, 0.0), z0_mm: float = 0.0) -> TriangleSurface:
    """Closed, outward-oriented triangulation of a solid cylinder (vertical axis) with edges of
    about ``spacing_mm``; every vertex lies on the exact surface."""
    n_theta = max(12, math.ceil(2 * math.pi * radius_mm / spacing_mm))
    n_z = max(1, math.ceil(height_mm / spacing_mm))
    theta = 2 * math.pi * np.arange(n_theta) / n_theta
    ring = radius_mm * np.column_stack([np.cos(theta), np.sin(theta)])
    z = z0_mm + np.linspace(0.0, height_mm, n_z + 1)
    verts = [np.column_stack([np.tile(ring, (n_z + 1, 1)), np.repeat(z, n_theta)])]
    a = np.arange(n_z)[:, None] * n_theta + np.arange(n_theta)[None, :]
    b = np.arange(n_z)[:, None] * n_theta + (np.arange(n_theta)[None, :] + 1) % n_theta
    a, b = a.ravel(), b.ravel()
    tris = [np.column_stack([a, b, b + n_theta]), np.column_stack([a, b + n_theta, a + n_theta])]
    inner = _disk_points(radius_mm, spacing_mm)
    start = len(verts[0])
    from scipy.spatial import Delaunay

    for zc, ring_first, up in ((z[0], 0, False), (z[-1], n_z * n_theta, True)):
        verts.append(np.column_stack([inner, np.full(len(inner), zc)]))
        ids = np.concatenate([ring_first + np.arange(n_theta), start + np.arange(len(inner))])
        cap = ids[Delaunay(np.vstack([ring, inner])).simplices]
        tris.append(_orient_z(cap, np.vstack(verts), up))
        start += len(inner)
    v = np.vstack(verts)
    v[:, :2] += np.asarray(center_mm, float)
    t = np.vstack(tris)
    return TriangleSurface(v, t)


def _disk_points(radius_mm: float, spacing_mm: float) -> np.ndarray:
    """Concentric rings of points strictly inside a disk, about ``spacing_mm`` apart."""
    n_r = max(1, math.ceil(radius_mm / spacing_mm))
    pts = [np.zeros((1, 2))]
    for i in range(1, n_r):
        r = radius_mm * i / n_r
        m = max(6, math.ceil(2 * math.pi * r / spacing_mm))
        phi = 2 * math.pi * (np.arange(m) + 0.5 * (i % 2)) / m
        pts.append(r * np.column_stack([np.cos(phi), np.sin(phi)]))
    return np.vstack(pts)


def _orient_z(tris: np.ndarray, verts: np.ndarray, up: bool) -> np.ndarray:
    """Flip the cap triangles whose normal does not point along ±z as asked."""
    p = verts[tris]
    nz = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])[:, 2]
    flip = (nz < 0) if up else (nz > 0)
    out = tris.copy()
    out[flip] = tris[flip][:, ::-1]
    return out


def decimated_surface(vertices: np.ndarray, triangles: np.ndarray,
                      spacing_mm: float) -> TriangleSurface:
    """A fine closed mesh decimated (VTK quadric decimation) to triangles of about
    ``spacing_mm`` (the area of an equilateral triangle with that edge)."""
    import pyvista as pv

    faces = np.hstack([np.full((len(triangles), 1), 3), triangles]).ravel()
    poly = pv.PolyData(np.asarray(vertices, float), faces)
    target = poly.area / (math.sqrt(3) / 4 * spacing_mm ** 2)
    if target < len(triangles):
        poly = poly.decimate(1.0 - target / len(triangles))
    out = TriangleSurface(np.asarray(poly.points), poly.faces.reshape(-1, 4)[:, 1:])
    problems = closed_manifold_problems(out)
    if problems:
        raise DeviceError("sim-laser: the sample mesh could not be decimated to a closed "
                          f"surface at {spacing_mm} mm (" + "; ".join(problems) + "); choose "
                          "another node_spacing_mm.")
    return out


def true_surface(shape, spacing_mm: float) -> TriangleSurface:
    """Closed surface of the sample shape (sample frame, mm) at about ``spacing_mm``."""
    if isinstance(shape, Cylinder):
        return cylinder_surface(shape.radius, shape.height, spacing_mm, shape.center, shape.z0)
    if isinstance(shape, MeshShape):
        return decimated_surface(shape.vertices, shape.triangles, spacing_mm)
    raise DeviceError(f"sim-laser: cannot trans-illuminate a {type(shape).__name__} sample; "
                      "use a cylinder or a mesh phantom.")


def tetrahedralize(surface: TriangleSurface, spacing_mm: float) -> TetMesh:
    """Quality tetrahedra (TetGen: radius–edge ≤ 1.5, dihedral ≥ 15°) filling ``surface``,
    with elements no larger than 1.6 regular tetrahedra of edge ``spacing_mm``."""
    import tetgen

    tg = tetgen.TetGen(surface.vertices, surface.triangles.astype(np.int32))
    vmax = 1.6 * spacing_mm ** 3 / (6.0 * math.sqrt(2.0))
    try:
        nodes, tets, *_ = tg.tetrahedralize(quality=True, minratio=1.5, mindihedral=15.0,
                                            fixedvolume=True, maxvolume=vmax, quiet=True,
                                            nowarning=True)
    except RuntimeError as exc:
        raise DeviceError(f"sim-laser: TetGen could not fill the sample ({exc}); choose "
                          "another node_spacing_mm.") from None
    nodes = np.asarray(nodes, float)
    return compact(nodes, orient_positive(nodes, np.asarray(tets)[:, :4]))


# ---- the FEM of one sample ---------------------------------------------------------------

@dataclass
class FluenceModel:
    """Tetrahedral mesh of the true sample, its optics, the FEM system and solved sources."""

    mesh: TetMesh
    optics: Optics
    matrix: sp.csr_matrix
    boundary: TriangleBVH    # the FEM boundary, for reading φ at surface points
    key: str
    _solved: OrderedDict = field(default_factory=OrderedDict)

    @classmethod
    def build(cls, surface: TriangleSurface, optics: Optics, spacing_mm: float,
              key: str = "") -> FluenceModel:
        from dotshell.fem.forward import robin_A, system_matrix

        mesh = tetrahedralize(surface, spacing_mm)
        n = len(mesh.nodes)
        mua = np.full(n, optics.mua_per_mm)
        kappa = np.full(n, 1.0 / (3.0 * (optics.mua_per_mm + optics.musp_per_mm)))
        matrix = system_matrix(mesh, mua, kappa, robin_A(optics.n)).tocsr()
        return cls(mesh, optics, matrix, TriangleBVH(mesh.nodes, mesh.boundary_faces), key)

    def source_inside(self, entry_mm: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """The source point: one transport length inside the entry point along the beam, or
        (grazing entry, that point outside the mesh) below the surface along its normal."""
        depth = self.optics.transport_length_mm
        along = np.asarray(entry_mm, float) + depth * np.asarray(direction, float)
        try:
            element_containing(self.mesh, along)
            return along
        except MeshError:
            from dotshell.fem.forward import move_inside

            return move_inside(self.mesh, entry_mm, depth)

    def fluence(self, source_mm: np.ndarray) -> np.ndarray:
        """φ per node (1/mm² per unit power) for a unit point source at ``source_mm``."""
        return cached(self._solved, tuple(np.round(source_mm, 6)),
                      lambda: self._solve(source_mm), 64)

    def _solve(self, source_mm: np.ndarray) -> np.ndarray:
        from dotshell.fem.forward import jacobi_cg

        el, w = element_containing(self.mesh, source_mm)
        q = np.zeros(len(self.mesh.nodes))
        q[self.mesh.tets[el]] = w
        try:
            return jacobi_cg(self.matrix, q)
        except MeshError as exc:
            raise DeviceError(f"sim-laser: {exc}") from None

    def surface_fluence(self, phi: np.ndarray, points_mm: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
        """φ at surface points (snapped to the FEM boundary) and their distance to it (mm)."""
        at = self.boundary.closest(points_mm)
        return at.interpolate(phi), at.distance_mm


_MODELS: OrderedDict[str, FluenceModel] = OrderedDict()
_MAX_MODELS = 3


def shape_key(shape) -> str:
    """Identity of a sample shape's geometry (for caching its FEM)."""
    if isinstance(shape, Cylinder):
        return f"cylinder {shape.radius} {shape.height} {tuple(shape.center)} {shape.z0}"
    if isinstance(shape, MeshShape):
        h = hashlib.sha1(np.ascontiguousarray(shape.vertices, float).tobytes())
        h.update(np.ascontiguousarray(shape.triangles, np.int64).tobytes())
        return f"mesh {h.hexdigest()}"
    return f"{type(shape).__name__} {id(shape)}"


def fluence_model(shape, optics: Optics, spacing_mm: float) -> FluenceModel:
    """The (in-process cached) FEM of a sample shape with these optics and node spacing."""
    key = f"{shape_key(shape)} {optics} {spacing_mm}"
    return cached(_MODELS, key, lambda: FluenceModel.build(true_surface(shape, spacing_mm),
                                                           optics, spacing_mm, key), _MAX_MODELS)


def compile_kernels() -> None:
    """Call the FEM truth's compiled kernels (TetGen's mesh checks, the system matrix, the
    conjugate gradients, the boundary's closest points) on a small cylinder, with the argument
    types a laser view passes: the sim-laser backend's
    :attr:`~dotshell.backends.Backend.compile_kernels`."""
    model = FluenceModel.build(cylinder_surface(4.0, 6.0, 2.0), Optics(0.01, 1.0, 1.37), 2.0)
    entry, direction = np.array([-4.0, 0.0, 3.0]), np.array([1.0, 0.0, 0.0])
    phi = model.fluence(model.source_inside(entry, direction))
    model.surface_fluence(phi, np.array([[4.0, 0.0, 3.0], [0.0, 4.1, 2.0]]))
    from dotshell.fem.forward import move_inside

    move_inside(model.mesh, entry, 1.0)


# ---- the beam ----------------------------------------------------------------------------

def beam_in_sample_frame(angle_deg: float, target_mm) -> tuple[np.ndarray, np.ndarray]:
    """Start point and unit direction of the beam in the sample frame at stage angle θ."""
    y, z = (float(v) for v in target_mm)
    R = rot_z(angle_deg)  # sample → stage; stage → sample is R.T
    start = R.T @ np.array([_BEAM_START_MM, y, z])
    return start, R.T @ np.array([1.0, 0.0, 0.0])


def beam_entry(shape, angle_deg: float, target_mm) -> tuple[np.ndarray, np.ndarray] | None:
    """Where the beam enters the sample (sample frame, mm) and its direction; None = misses."""
    start, d = beam_in_sample_frame(angle_deg, target_mm)
    with np.errstate(invalid="ignore", divide="ignore"):  # a level beam meets no cap
        t, _ = shape.intersect(start[None, :], d[None, :])
    if not np.isfinite(t[0]):
        return None
    return start + t[0] * d, d


def sample_extent_text(shape, angle_deg: float) -> str:
    """'y … mm, z … mm': the sample's extent across the beam (stage frame) at angle θ."""
    if isinstance(shape, Cylinder):
        phi = np.linspace(0, 2 * np.pi, 721)
        ring = np.column_stack([shape.center[0] + shape.radius * np.cos(phi),
                                shape.center[1] + shape.radius * np.sin(phi)])
        pts = np.vstack([np.column_stack([ring, np.full(len(ring), zc)])
                         for zc in (shape.z0, shape.z0 + shape.height)])
    else:
        pts = np.asarray(shape.vertices, float)
    stage = pts @ rot_z(angle_deg).T
    return (f"y {stage[:, 1].min():.1f} to {stage[:, 1].max():.1f} mm, "
            f"z {stage[:, 2].min():.1f} to {stage[:, 2].max():.1f} mm")


def require_entry(shape, angle_deg: float, target_mm, who: str = "sim-laser"
                  ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`beam_entry`, or a DeviceError naming the target and the sample's extent."""
    hit = beam_entry(shape, angle_deg, target_mm)
    if hit is None:
        y, z = target_mm
        raise DeviceError(
            f"{who}: the beam at target (y, z) = ({y:g}, {z:g}) mm misses the sample at stage "
            f"angle {angle_deg:g}°; the sample spans {sample_extent_text(shape, angle_deg)} "
            "across the beam (stage frame). Aim inside that range.")
    return hit


# ---- rendering ---------------------------------------------------------------------------

@dataclass
class LaserView:
    """Camera sub-samples whose first hit is the sample, at one stage angle: their camera
    pixel, boundary nodes and weights, and radiance-per-fluence × cos⁴ fall-off."""

    pixel: np.ndarray        # (K,) int32: flat camera pixel index (row · W + col)
    nodes: np.ndarray        # (K, 3) int: FEM boundary nodes of the closest triangle
    weights: np.ndarray      # (K, 3) float32 barycentric weights
    base: np.ndarray         # (K,) float32: L(θo)/φ · cos⁴(field angle) / ss²
    shape: tuple[int, int]   # (H, W)
    images: OrderedDict = field(default_factory=OrderedDict)


#: Sub-samples traced at a time by :func:`laser_view`: its float64 temporaries (~0.25 KB a
#: sample) stay ~60 MB, where the ~2.7 M samples of a full-resolution agar view at once took
#: ~0.7 GB above the rest of the scan (issue 33; the arrays are the same bit for bit).
LASER_CHUNK = 1 << 18


def laser_view(renderer: Renderer, view: View, shape, model: FluenceModel) -> LaserView:
    """Trace the camera sub-samples that see the sample (first hit, from ``view``) to the true
    sample surface and locate them on the FEM boundary, :data:`LASER_CHUNK` at a time."""
    cam = renderer.calib.camera
    k = np.flatnonzero(view.material.ravel() == shape.material)
    o_s = renderer.calib.camera_to_sample(np.zeros((1, 3)), view.angle_deg)[0]
    M = renderer.calib.sample_rotation(view.angle_deg)
    # the arrays are filled chunk by chunk in place: chunks then concatenated held the ~0.1 GB
    # laser view twice at the scan's peak (issue 33); int32 pixels (the same indices)
    n = len(k)
    pixel, nodes = np.empty(n, np.int32), np.empty((n, 3), np.int32)
    weights, base = np.empty((n, 3), np.float32), np.empty(n, np.float32)
    filled = 0
    for s in range(0, n, LASER_CHUNK):
        part = _laser_samples(k[s:s + LASER_CHUNK], renderer, o_s, M, view.ss, cam.width,
                              shape, model)
        end = filled + len(part[0])
        for whole, values in zip((pixel, nodes, weights, base), part):
            whole[filled:end] = values
        filled = end
    return LaserView(pixel[:filled], nodes[:filled], weights[:filled], base[:filled],
                     (cam.height, cam.width))


def _laser_samples(k: np.ndarray, renderer: Renderer, o_s: np.ndarray, M: np.ndarray,
                   ss: int, width: int, shape, model: FluenceModel
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`laser_view`'s (pixel, nodes, weights, base) of the sub-samples ``k`` (flat
    indices on the supersampled grid) that hit the true surface; their rays are made for
    them (:meth:`Renderer.sample_rays`: the whole image's 120 MiB of float64 rays were made
    again for each full-resolution laser view, issue 33)."""
    d_c = renderer.sample_rays(k)
    d_s = d_c @ M
    t, normals = shape.intersect(np.broadcast_to(o_s, d_s.shape), d_s)
    ok = np.isfinite(t)
    k, d_c, d_s, t, normals = k[ok], d_c[ok], d_s[ok], t[ok], normals[ok]
    points = o_s + t[:, None] * d_s
    cos_out = np.clip(-np.einsum("ij,ij->i", normals, d_s), 0.0, 1.0)  # towards the camera
    at = model.boundary.closest(points)
    base = exit_radiance_per_fluence(cos_out, model.optics.n) * d_c[:, 2] ** 4 / ss ** 2
    row, col = divmod(k, width * ss)
    pixel = (row // ss) * width + col // ss
    return (pixel, at.nodes.astype(np.int32), at.weights.astype(np.float32),
            base.astype(np.float32))


def emission_image(lv: LaserView, phi: np.ndarray) -> np.ndarray:
    """Relative image irradiance (H, W) float32 for unit beam power and node fluence ``phi``.
    The fluence at the sub-samples is made :data:`LASER_CHUNK` at a time from float32 node
    values (the same numbers: each sample's three corners cast, then weighted): all at once,
    through float64, took ~0.1 GB for a full-resolution agar view (issue 33)."""
    phi32 = np.asarray(phi).astype(np.float32)
    phi_k = np.empty(len(lv.pixel), np.float32)
    for s in range(0, len(phi_k), LASER_CHUNK):
        np.einsum("ij,ij->i", phi32[lv.nodes[s:s + LASER_CHUNK]], lv.weights[s:s + LASER_CHUNK],
                  out=phi_k[s:s + LASER_CHUNK])
    img = np.bincount(lv.pixel, phi_k * lv.base, lv.shape[0] * lv.shape[1])
    return img.reshape(lv.shape).astype(np.float32)


#: Laser views per renderer (renderers are shared by geometry and dropped with it).
_VIEWS: weakref.WeakKeyDictionary[Renderer, OrderedDict] = weakref.WeakKeyDictionary()


def release_laser_views(renderer: Renderer, keep_below_bytes: int = 0) -> None:
    """Forget ``renderer``'s laser views unless together they hold less than
    ``keep_below_bytes``: at full resolution the last trans-illumination angle's is ~0.12 GB,
    held after the rig closed through the scan's merge, validation and previews (issue 33)."""
    views = _VIEWS.get(renderer)
    if views and sum(a.nbytes for lv in views.values() for a in (lv.pixel, lv.nodes, lv.weights,
                                                                   lv.base)) >= keep_below_bytes:
        views.clear()


def laser_irradiance(renderer: Renderer, view: View, shape, model: FluenceModel,
                     target_mm) -> np.ndarray:
    """Relative image irradiance (H, W) float32 from a unit-power beam at ``target_mm``
    with the stage at ``view.angle_deg`` (cached per renderer, angle and target)."""
    views = _VIEWS.setdefault(renderer, OrderedDict())
    key = (model.key, view.angle_deg)
    if key not in views:  # one angle's at a time, dropped before the next is traced (~0.1 GB)
        views.clear()
    lv = cached(views, key, lambda: laser_view(renderer, view, shape, model), 1)

    def image() -> np.ndarray:
        entry, direction = require_entry(shape, view.angle_deg, target_mm)
        return emission_image(lv, model.fluence(model.source_inside(entry, direction)))

    return cached(lv.images, tuple(round(float(v), 9) for v in target_mm), image, 8)


# ---- lens fall-off -----------------------------------------------------------------------

def natural_falloff(lens: Lens) -> np.ndarray:
    """cos⁴ of the field angle at every pixel centre (H, W) float32 (the renderer's natural
    vignetting)."""
    w, h = lens.size
    d = lens.rays(subpixel_grid(w, h, 1))
    return (d[:, 2] ** 4).reshape(h, w).astype(np.float32)


def lens_vignetting(lens: Lens, loss_at_corner: float) -> np.ndarray:
    """Extra lens vignetting (H, W) float32: ``1 − loss · (r / r_corner)²``, r the distance from
    the principal point (px), r_corner that of the farthest image corner."""
    w, h = lens.size
    cx, cy = lens.K[0, 2], lens.K[1, 2]
    u, v = np.meshgrid(np.arange(w) - cx, np.arange(h) - cy)
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    r2_corner = float(np.max(np.sum((corners - [cx, cy]) ** 2, axis=1)))
    return (1.0 - loss_at_corner * (u * u + v * v) / r2_corner).astype(np.float32)
