"""Scene geometry for the simulator: shapes that intersect rays exactly, and materials.

Interface: a *shape* has ``intersect(origins, dirs) -> (t, normals)`` with ``t`` = +inf where
the ray misses, and a ``material`` index. A :class:`Scene` is a list of shapes plus their
materials; its ``intersect(origins, dirs) -> (t, normals, material_id)`` returns the nearest hit
(``material_id`` = -1 on a miss). All lengths in mm, directions unit vectors, arrays (N, 3)
float64; normals are unit and face the incoming ray's side for open surfaces (planes, disks) and
outwards for closed ones.

:class:`StagedScene` combines the *sample* (cylinder, plate; expressed in the sample frame and
turning with the stage) and the *fixed* surroundings (background; expressed in the stage frame,
i.e. the sample frame at 0°). ``at(angle_deg)`` gives a :class:`Scene` in the sample frame for one
stage angle — see :mod:`dotshell.geometry.calibration` for the frames.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, Sequence

import numpy as np

from dotshell.geometry.raycast import TriangleScene

from dotshell.geometry.calibration import rot_z

from dotshell_sim.subsurface import Scattering
from dotshell_sim import phantoms as _phantoms


@dataclass(frozen=True)
class Material:
    """Reflectance of an opaque surface.

    Attributes:
        name: short name.
        albedo: Lambertian (diffuse) albedo at the surface, 0..1.
        specular: weight of the normalized Blinn–Phong lobe, ``ks·(n+8)/8·(N·H)^n``
            relative to a white Lambertian surface; 0 for a matte surface.
        shininess: Blinn–Phong exponent ``n`` (larger = sharper highlight).
        depolarization: share of the diffuse surface reflection that loses the projector's
            polarization (1 for paper-like surfaces; specular reflection always keeps it).
        scattering: subsurface transport of light entering the material (None = opaque).
    """

    name: str
    albedo: float
    specular: float = 0.0
    shininess: float = 1.0
    depolarization: float = 1.0
    scattering: Scattering | None = None


#: Built-in materials by name (the turntable's ``scene.material`` etc. choose among these).
MATERIALS: dict[str, Material] = {
    # turned / lightly brushed aluminium or steel: greyish diffuse part and a broad highlight;
    # metal reflection keeps most of the polarization
    "metal": Material("metal", albedo=0.40, specular=0.25, shininess=60.0, depolarization=0.2),
    # 2 % agar gel at ~750 nm (docs/light-model.md): a glossy wet surface (Fresnel R0 = 2 % at
    # n = 1.33) with weak single scattering at the surface that keeps the polarization, and
    # strong diffuse subsurface transport (μs' = 1/mm, μa = 0.01/mm) that does not
    "agar": Material("agar", albedo=0.03, specular=0.02, shininess=300.0, depolarization=0.0,
                     scattering=Scattering(mus_prime_per_mm=1.0, mua_per_mm=0.01, n=1.33)),
    # anodized grey stage plate
    "plate": Material("plate", albedo=0.35, specular=0.03, shininess=10.0),
    # black flock / velvet behind the sample
    "background": Material("background", albedo=0.03),
    # matte white (spray-painted) calibration object
    "matte-white": Material("matte-white", albedo=0.85),
    # mid-grey matte object
    "matte-grey": Material("matte-grey", albedo=0.45),
}
# gelatine gummy bear (dotshell_sim.phantoms; opaque stand-in without the subsurface model)
MATERIALS["gummy"] = _phantoms.gummy_material(Material)

_EPS = 1e-9


class Shape(Protocol):
    material: int

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest hit distance ``t`` (N,) (+inf = miss, only t > 0) and unit normals (N, 3)."""
        ...


def _facing(normals: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Flip normals to face against the ray directions (for two-sided open surfaces)."""
    s = np.where(np.einsum("ij,ij->i", normals, dirs) > 0, -1.0, 1.0)
    return normals * s[:, None]


@dataclass
class Cylinder:
    """Solid circular cylinder with a vertical axis (sample-frame z), exact intersection.

    Attributes:
        radius: mm.
        height: mm; the cylinder spans z in [z0, z0 + height].
        center: (x, y) of its axis in the sample frame, mm.
        z0: bottom, mm (0 = standing on the stage plate).
        top_cap, bottom_cap: whether the flat ends exist as surfaces.
        material: index into the scene's materials.
    """

    radius: float
    height: float
    center: tuple[float, float] = (0.0, 0.0)
    z0: float = 0.0
    top_cap: bool = True
    bottom_cap: bool = False
    material: int = 0

    def intersect(self, origins, dirs):
        return self._hits(origins, dirs, True)

    def distances(self, origins, dirs):
        """``intersect``'s ``t`` alone (shadow rays need no normals)."""
        return self._hits(origins, dirs, False)[0]

    def _hits(self, origins, dirs, with_normals: bool):
        n = len(origins)
        ox = origins[:, 0] - self.center[0]
        oy = origins[:, 1] - self.center[1]
        oz = origins[:, 2]
        dx, dy, dz = dirs[:, 0], dirs[:, 1], dirs[:, 2]
        r2 = self.radius * self.radius
        z1 = self.z0 + self.height
        t_best = np.full(n, np.inf)
        normals = np.zeros((n, 3)) if with_normals else None

        # side: (ox + t dx)^2 + (oy + t dy)^2 = r^2, numerically stable roots
        a = dx * dx + dy * dy
        b = ox * dx + oy * dy
        c = ox * ox + oy * oy - r2
        disc = b * b - a * c
        ok = (disc >= 0) & (a > _EPS)
        with np.errstate(invalid="ignore", divide="ignore"):
            sq = np.sqrt(np.where(ok, disc, 0.0))
            q = -(b + np.copysign(sq, b))
            t1 = q / a
            t2 = c / q
        tn = np.where(ok, np.minimum(t1, t2), np.inf)
        tf = np.where(ok, np.maximum(t1, t2), np.inf)
        for t in (tn, tf):  # nearest root with t > 0 inside the height range
            z = oz + t * dz
            good = ok & (t > _EPS) & (z >= self.z0) & (z <= z1) & (t < t_best)
            t_best = np.where(good, t, t_best)
            if with_normals and good.any():
                px = ox[good] + t[good] * dx[good]
                py = oy[good] + t[good] * dy[good]
                normals[good] = np.column_stack([px, py, np.zeros(good.sum())]) / self.radius
        # caps
        caps = []
        if self.top_cap:
            caps.append((z1, 1.0))
        if self.bottom_cap:
            caps.append((self.z0, -1.0))
        for zc, nz in caps:
            with np.errstate(invalid="ignore", divide="ignore"):
                t = (zc - oz) / dz
            px = ox + t * dx
            py = oy + t * dy
            good = (np.abs(dz) > _EPS) & (t > _EPS) & (px * px + py * py <= r2) & (t < t_best)
            t_best = np.where(good, t, t_best)
            if with_normals:
                normals[good] = (0.0, 0.0, nz)
        return t_best, normals


@dataclass
class Disk:
    """Horizontal disk z = ``z`` of radius ``radius`` centred on (``center``), two-sided."""

    radius: float
    z: float = 0.0
    center: tuple[float, float] = (0.0, 0.0)
    material: int = 0

    def intersect(self, origins, dirs):
        t = self.distances(origins, dirs)
        dz = dirs[:, 2]
        normals = np.zeros((len(origins), 3))
        normals[:, 2] = np.where(dz > 0, -1.0, 1.0)
        return t, normals

    def distances(self, origins, dirs):
        """``intersect``'s ``t`` alone (shadow rays need no normals)."""
        dz = dirs[:, 2]
        with np.errstate(invalid="ignore", divide="ignore"):
            t = (self.z - origins[:, 2]) / dz
        px = origins[:, 0] + t * dirs[:, 0] - self.center[0]
        py = origins[:, 1] + t * dirs[:, 1] - self.center[1]
        good = (np.abs(dz) > _EPS) & (t > _EPS) & (px * px + py * py <= self.radius ** 2)
        return np.where(good, t, np.inf)


@dataclass
class Plane:
    """Infinite plane ``normal · X = offset`` (two-sided)."""

    normal: tuple[float, float, float]
    offset: float
    material: int = 0

    def intersect(self, origins, dirs):
        t = self.distances(origins, dirs)
        nrm = self._unit_normal()
        normals = _facing(np.broadcast_to(nrm, dirs.shape).copy(), dirs)
        return t, normals

    def distances(self, origins, dirs):
        """``intersect``'s ``t`` alone (shadow rays need no normals)."""
        nrm = self._unit_normal()
        den = dirs @ nrm
        with np.errstate(invalid="ignore", divide="ignore"):
            t = (self.offset - origins @ nrm) / den
        good = (np.abs(den) > _EPS) & (t > _EPS)
        return np.where(good, t, np.inf)

    def _unit_normal(self) -> np.ndarray:
        nrm = np.asarray(self.normal, float)
        return nrm / np.linalg.norm(nrm)

    def rotated_z(self, angle_deg: float) -> Plane:
        """The plane given in the stage frame, in the sample frame at stage angle θ
        (``p_stage = Rz(θ) p_sample``, so ``n · Rz p = (Rzᵀ n) · p``): a plane again."""
        return Plane(tuple(rot_z(angle_deg).T @ np.asarray(self.normal, float)), self.offset,
                     self.material)


@dataclass
class MeshShape:
    """Triangle mesh (closed or not) intersected with open3d's ``RaycastingScene``.

    Float32 inside open3d: hits are accurate to ~1e-5 mm at 200 mm, fine for objects whose
    shape is itself the mesh (not for approximating analytic shapes — use those instead).
    """

    vertices: np.ndarray
    triangles: np.ndarray
    material: int = 0
    _scene: object = field(default=None, repr=False)

    def _raycaster(self) -> TriangleScene:
        if self._scene is None:  # lazy: only mesh scenes need open3d
            self._scene = TriangleScene(self.vertices, self.triangles)
        return self._scene

    def intersect(self, origins, dirs):
        ans = self._raycaster().cast(origins, dirs)
        t = ans["t_hit"].astype(np.float64)
        t[~np.isfinite(t) | (t <= _EPS)] = np.inf
        normals = ans["primitive_normals"].astype(np.float64)
        nn = np.linalg.norm(normals, axis=1, keepdims=True)
        normals = normals / np.where(nn > 0, nn, 1.0)
        return t, _facing(normals, dirs)


class Scene:
    """Shapes plus the materials they refer to (by index)."""

    def __init__(self, shapes: Sequence[Shape], materials: Sequence[Material]):
        self.shapes = list(shapes)
        self.materials = list(materials)

    def intersect(self, origins: np.ndarray, dirs: np.ndarray):
        """Nearest hit over all shapes: ``t`` (N,), unit normals (N, 3), material id (N,) int
        (-1 = miss)."""
        origins = np.asarray(origins, float)
        dirs = np.asarray(dirs, float)
        n = len(origins)
        t_best = np.full(n, np.inf)
        normals = np.zeros((n, 3))
        mat = np.full(n, -1, dtype=np.int16)
        for shape in self.shapes:
            t, nrm = shape.intersect(origins, dirs)
            closer = t < t_best
            t_best = np.where(closer, t, t_best)
            normals[closer] = nrm[closer]
            mat[closer] = shape.material
        return t_best, normals, mat

    def blocked(self, origins: np.ndarray, dirs: np.ndarray, t_max: np.ndarray) -> np.ndarray:
        """Whether each ray hits a shape before ``t_max`` (N,) (mm): the shadow test, the same
        as ``intersect``'s nearest ``t < t_max`` without its normals and materials (a third of
        a view's tracing went into the shadow rays' normals)."""
        origins = np.asarray(origins, float)
        dirs = np.asarray(dirs, float)
        out = np.zeros(len(origins), bool)
        for shape in self.shapes:
            out |= _distances(shape, origins, dirs) < t_max
        return out


def _distances(shape: Shape, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """A shape's hit distances ``t`` (N,): its ``distances`` where it has one (no normals)."""
    distances = getattr(shape, "distances", None)
    return distances(origins, dirs) if distances is not None else shape.intersect(origins, dirs)[0]


class _RotatedShape:
    """A shape given in the stage frame, seen from the sample frame at stage angle θ."""

    def __init__(self, shape: Shape, angle_deg: float):
        self.shape = shape
        self.material = shape.material
        self.R = rot_z(angle_deg)  # sample → stage: p_stage = Rz(θ) p_sample

    def intersect(self, origins, dirs):
        t, nrm = self.shape.intersect(origins @ self.R.T, dirs @ self.R.T)
        return t, nrm @ self.R

    def distances(self, origins, dirs):
        return _distances(self.shape, origins @ self.R.T, dirs @ self.R.T)


class StagedScene:
    """Sample shapes (turning with the stage) + fixed shapes (stage frame), shared materials."""

    def __init__(self, sample: Sequence[Shape], fixed: Sequence[Shape],
                 materials: Sequence[Material]):
        self.sample = list(sample)
        self.fixed = list(fixed)
        self.materials = list(materials)

    def turns_into_itself(self) -> bool:
        """Whether turning the stage leaves the scene as it is: every sample shape is symmetric
        about the turntable axis (the sample frame's z axis). A view of such a scene is then the
        same at every stage angle (the fixed shapes do not turn, and neither does anything the
        camera and projector see of the sample)."""
        return all(_symmetric_about_axis(s) for s in self.sample)

    def at(self, angle_deg: float) -> Scene:
        """The scene in the sample frame with the stage at ``angle_deg``."""
        return Scene(self.sample + [_rotated(s, angle_deg) for s in self.fixed], self.materials)


def _symmetric_about_axis(shape: Shape) -> bool:
    """Whether ``shape`` (sample frame) is its own image under any turn about the z axis."""
    if isinstance(shape, (Cylinder, Disk)):
        return tuple(shape.center) == (0.0, 0.0)
    if isinstance(shape, Plane):
        return shape.normal[0] == 0.0 and shape.normal[1] == 0.0
    return False  # meshes and anything else: assume not


def _rotated(shape: Shape, angle_deg: float) -> Shape:
    """A stage-frame shape seen from the sample frame at ``angle_deg``: shapes that can turn
    themselves (a plane) do, which spares rotating every ray twice per intersection."""
    if hasattr(shape, "rotated_z"):
        return shape.rotated_z(angle_deg)
    return _RotatedShape(shape, angle_deg)


def build_scene(sample: dict, plate: dict, background: dict) -> StagedScene:
    """The turntable's scene from its (validated) settings tables.

    Args:
        sample: ``kind`` ("cylinder" | "none"), ``radius_mm``, ``height_mm``, ``offset_mm``
            (x, y of the axis in the sample frame), ``material``.
        plate: ``radius_mm`` (0 = no plate), ``material``.
        background: ``distance_mm`` (behind the turntable axis, away from the camera; 0 = none),
            ``material``.
    """
    materials: list[Material] = []

    def mat(name: str) -> int:
        materials.append(MATERIALS[name])
        return len(materials) - 1

    shapes: list[Shape] = []
    if sample["kind"] == "cylinder":
        shapes.append(Cylinder(sample["radius_mm"], sample["height_mm"],
                               center=tuple(sample["offset_mm"]), material=mat(sample["material"])))
    elif sample["kind"] in _phantoms.PHANTOMS:  # procedural mesh phantoms, fixed size
        verts, tris = _phantoms.phantom_mesh(sample["kind"])
        shift = np.array([*sample["offset_mm"], 0.0])
        shapes.append(MeshShape(verts + shift, tris, material=mat(sample["material"])))
    if plate["radius_mm"] > 0:
        shapes.append(Disk(plate["radius_mm"], z=0.0, material=mat(plate["material"])))
    fixed: list[Shape] = []
    if background["distance_mm"] > 0:
        # stage frame: +x points towards the camera, so "behind" is x = -distance
        fixed.append(Plane((1.0, 0.0, 0.0), -background["distance_mm"],
                           material=mat(background["material"])))
    return StagedScene(shapes, fixed, materials)
