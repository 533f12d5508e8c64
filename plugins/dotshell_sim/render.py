"""Pure rendering of the simulated rig: ray tracing per view, texture sampling per frame, sensor.

Pipeline:

1. :meth:`Renderer.trace` — for camera pixel positions (distorted, OpenCV convention) and a stage
   angle: camera rays (``Lens.rays``) → sample frame (``RigCalibration.camera_to_sample``) →
   exact scene intersection → shadow ray to the projector centre → projector pixel of every hit
   (projector distortion included) → shading weights. Everything in float64.
2. :meth:`Renderer.view` — ``trace`` on a supersampled pixel grid (``ss × ss`` sub-pixel rays per
   camera pixel), stored as float32 maps and cached per stage angle (geometry does not change
   between patterns).
3. :meth:`Renderer.render` — per pattern: projector defocus (Gaussian), bilinear texture lookup
   at the precomputed projector coordinates, × weights, box-average of the sub-pixel samples,
   + ambient, camera defocus → expected electrons per pixel.
4. :func:`sensor` — shot noise, read noise, full-well clipping, dark offset, ADC quantization.

Radiometry (relative units; 1.0 = a white Lambertian surface facing the projector at the
projector's reference distance, lit by full projector brightness)::

    w = vis · (albedo + ks·(n+8)/8·(N·H)^n) · cos_i · (d_ref / d_p)^2 · cos^4(field angle)

with ``cos_i = N·L`` (L towards the projector centre), H the half vector between L and the
direction to the camera, ``d_p`` the distance to the projector, ``vis`` 0 in the projector's
shadow or outside its image. Ambient light adds ``ambient · albedo · cos^4`` everywhere.
Electrons = ``sensitivity_e_per_ms · exposure_ms · (projector radiance · w + ambient term)``.
"""

from __future__ import annotations

import dataclasses
import math
from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np

from dotshell.runtime import hugepages
from dotshell.geometry.calibration import RigCalibration
from dotshell.geometry.lens import Lens, distort_normalized

from dotshell_sim.scene import StagedScene
from dotshell_sim.subsurface import SubsurfaceView, fresnel_transmittance, gaussian_mixture

# rays per chunk: an (N, 3) float64 temporary of a chunk (768 KiB) stays under the 1 MiB mmap
# threshold the process sets (dotshell.runtime.process.fix_mmap_threshold), so the dozens of temporaries
# of a trace come from the heap; at 1 << 16 each was a fresh mapping whose pages faulted in, and
# a view took 2.5-3x as long (6 views at 320x256, 2x2 supersampled: 7.5 -> 2.7 s of CPU)
_CHUNK = 1 << 15
_SHADOW_OFFSET = 1e-5     # mm, shadow-ray origin offset along the normal (avoids self-hits)
_OUTSIDE = -1.0e4         # projector coordinate used for "no projector light" (samples 0)


def project_points(lens: Lens, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vectorized ``Lens.project`` (same Brown–Conrady model as OpenCV, ~20x faster).

    Returns distorted pixel coordinates (N, 2) and a validity mask: in front of the lens and
    within 1.5x the image's field (beyond that the polynomial distortion may fold back and
    return a wrong pixel inside the image).
    """
    p = np.asarray(points, float).reshape(-1, 3)
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = p[:, 0] / z
        y = p[:, 1] / z
    K = lens.K
    fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    half_x = 1.5 * max(cx + 0.5, lens.width - 0.5 - cx) / fx
    half_y = 1.5 * max(cy + 0.5, lens.height - 0.5 - cy) / fy
    valid = (z > 0) & (np.abs(x) <= half_x) & (np.abs(y) <= half_y)
    x = np.where(valid, x, 0.0)
    y = np.where(valid, y, 0.0)
    xd, yd = distort_normalized(lens.dist, x, y)
    return np.column_stack([fx * xd + skew * yd + cx, fy * yd + cy]), valid


def subpixel_grid(width: int, height: int, ss: int, start: int = 0,
                  stop: int | None = None) -> np.ndarray:
    """Camera pixel coordinates (N, 2) of an ``ss × ss`` grid of sub-pixel sample centres per
    pixel, in row-major order of the supersampled image (ss·height, ss·width); samples
    ``start:stop`` of that order (default all)."""
    k = np.arange(start, width * height * ss * ss if stop is None else stop)
    row, col = np.divmod(k, width * ss)
    return np.column_stack([(col + 0.5) / ss - 0.5, (row + 0.5) / ss - 0.5])


@dataclass
class Trace:
    """Per-ray results of :meth:`Renderer.trace` (N rays; camera frame unless noted)."""

    pixels: np.ndarray       # (N, 2) camera pixel coordinates traced
    t: np.ndarray            # (N,) distance camera centre → hit (mm), inf on a miss
    points: np.ndarray       # (N, 3) hit points, camera frame (mm); NaN on a miss
    normals: np.ndarray      # (N, 3) unit surface normals, camera frame
    material: np.ndarray     # (N,) material id, -1 = miss
    projector: np.ndarray    # (N, 2) projector pixel coordinates of the hit (NaN if none)
    in_projector: np.ndarray  # (N,) hit is inside the projector image and faces it
    shadow: np.ndarray       # (N,) hit faces the projector but another surface blocks it
    weight: np.ndarray       # (N,) projector-light shading weight (0 where not lit)
    ambient: np.ndarray      # (N,) ambient shading weight (ambient · albedo · cos^4)
    weight_pol: np.ndarray   # (N,) share of ``weight`` that keeps the projector's polarization
    entering: np.ndarray     # (N,) irradiance entering a turbid material (T_in·cos_i·falloff·vign)

    @property
    def lit(self) -> np.ndarray:
        return self.weight > 0


@dataclass
class Light:
    """Relative image irradiance (H, W) split by polarization state."""

    polarized: np.ndarray    # keeps the projector's linear polarization
    depolarized: np.ndarray  # unpolarized (diffuse surfaces, subsurface light, room light)

    @property
    def total(self) -> np.ndarray:
        """Both states together (H, W), in lent memory (:mod:`dotshell.runtime.hugepages`)."""
        return np.add(self.polarized, self.depolarized,
                      out=hugepages.empty(np.broadcast_shapes(self.polarized.shape,
                                                              self.depolarized.shape),
                                          np.result_type(self.polarized, self.depolarized)))


#: Cached views a renderer keeps beyond its ``cache_views`` (and a closed camera leaves it)
#: while they hold less than this together (bytes): at reduced resolution (a few MB a view)
#: a rig scanned again, or another rig of the same geometry, reuses them; at full resolution
#: (~100 MB a view) only ``cache_views`` are kept and a closed camera frees them.
SMALL_VIEWS_BYTES = 64 * 2**20


def _array_bytes(obj: object, depth: int = 3, seen: set[int] | None = None) -> int:
    """Bytes of the numpy arrays in ``obj`` (a view: its attributes, lists and tuples), each
    array counted once (views of a symmetric scene share their maps)."""
    seen = set() if seen is None else seen
    if isinstance(obj, np.ndarray):
        if id(obj) in seen:
            return 0
        seen.add(id(obj))
        return obj.nbytes
    if depth == 0:
        return 0
    if isinstance(obj, (list, tuple)):
        return sum(_array_bytes(x, depth - 1, seen) for x in obj)
    if hasattr(obj, "__dict__"):
        return sum(_array_bytes(x, depth - 1, seen) for x in vars(obj).values())
    return 0


@dataclass
class View:
    """Precomputed per-view data on the supersampled grid (ss·H, ss·W) plus the ambient base."""

    angle_deg: float
    ss: int
    map_x: np.ndarray        # float32 projector column per sample (_OUTSIDE where unlit)
    map_y: np.ndarray        # float32 projector row per sample
    weight_dep: np.ndarray   # float32 shading weight per sample that loses the projector's
    #                          polarization: float32 total − float32 ``weight_pol`` (issue 33:
    #                          the total, kept beside it, was 21 MB more at full resolution)
    base: np.ndarray         # float32 (H, W) ambient weight, box-averaged (depolarized)
    material: np.ndarray     # int8 material id per sample (-1 = miss)
    shadow: np.ndarray       # bool per sample: cast shadow of the projector
    weight_pol: np.ndarray | None = None   # float32 polarization-keeping share of the weight
    entering: np.ndarray | None = None     # float32 irradiance into turbid material per sample
    subsurface: SubsurfaceView | None = None  # diffuse transport (depolarized)
    retained: tuple[float, float] = (0.0, 0.0)  # (share of R_total kept polarized, sigma px)
    seconds: float = 0.0     # time the precompute took

    @property
    def weight(self) -> np.ndarray:
        """float32 shading weight per sample (polarized + depolarized), made when asked (to
        float32 rounding of the total the view was traced with)."""
        return self.weight_dep if self.weight_pol is None else self.weight_dep + self.weight_pol

    def depolarized_weight(self) -> np.ndarray:
        """float32 share of the shading weight that loses the projector's polarization (per
        sample)."""
        return self.weight_dep

    def material_fraction(self, material_id: int) -> np.ndarray:
        """(H, W) fraction of each camera pixel's sub-samples that hit ``material_id``."""
        return _box(self.material == material_id, self.ss)

    def lit_fraction(self) -> np.ndarray:
        """(H, W) fraction of each camera pixel's sub-samples lit by the projector (both
        shares are ≥ 0: their sum is > 0 where the total weight is)."""
        return _box(self.weight > 0, self.ss)

    def shadow_fraction(self) -> np.ndarray:
        """(H, W) fraction of each camera pixel's sub-samples in the projector's cast shadow."""
        return _box(self.shadow, self.ss)


class _Receivers:
    """Accumulates, per camera pixel, the sub-samples that hit the turbid material."""

    def __init__(self, width: int, height: int, ss: int) -> None:
        self.width, self.height, self.ss = width, height, ss
        self.sums = np.zeros((width * height, 3))
        self.count = np.zeros(width * height)
        self.vign = np.zeros(width * height)

    def add(self, samples: np.ndarray, tr: Trace, material: int) -> None:
        sel = tr.material == material
        if not sel.any():
            return
        k = samples[sel]
        row, col = divmod(k, self.width * self.ss)
        pix = (row // self.ss) * self.width + col // self.ss
        for axis in range(3):
            self.sums[:, axis] += np.bincount(pix, tr.points[sel, axis], self.sums.shape[0])
        self.count += np.bincount(pix, minlength=self.count.size)
        # cos^4 vignetting from the ray direction (camera frame) of each sample
        d = tr.points[sel] / tr.t[sel, None]
        self.vign += np.bincount(pix, d[:, 2] ** 4, self.count.size)

    def result(self, calib: RigCalibration, angle_deg: float):
        """(points in the sample frame, pixel index, pixel share × vignetting)."""
        pix = np.flatnonzero(self.count > 0)
        pts = self.sums[pix] / self.count[pix, None]
        weight = self.vign[pix] / self.ss ** 2
        return calib.camera_to_sample(pts, angle_deg), pix, weight


def _box(a: np.ndarray, ss: int) -> np.ndarray:
    h, w = a.shape[0] // ss, a.shape[1] // ss
    return a.reshape(h, ss, w, ss).mean(axis=(1, 3), dtype=np.float64).astype(np.float32)


class Renderer:
    """Renders one rig: true geometry (``calib``), scene, camera optics; caches views.

    Args:
        calib: ground-truth rig geometry (camera and projector lenses, pose, turntable axis).
        scene: the staged scene (sample + fixed surroundings).
        supersample: sub-pixel rays per camera pixel along each axis (1..4).
        ambient: ambient light level relative to full projector light (unitless).
        projector_ref_mm: distance at which projector irradiance is 1 (inverse-square falloff).
        cache_views: how many views (stage angles) to keep (~100 MB each at 1280×1024, 2×
            supersampled); a scan visits each angle once, its PDI, trans-illumination and
            laser frames reuse the current one. More are kept while all the cached views
            together hold less than :data:`SMALL_VIEWS_BYTES` (reduced resolutions: the next
            scan of the same rig finds its views made).
    """

    def __init__(self, calib: RigCalibration, scene: StagedScene, supersample: int = 2,
                 ambient: float = 0.01, projector_ref_mm: float = 200.0,
                 cache_views: int = 1):
        self.calib = calib
        self.scene = scene
        self.ss = int(supersample)
        self.ambient = float(ambient)
        self.projector_ref_mm = float(projector_ref_mm)
        self.cache_views = cache_views
        self._views: OrderedDict[float, View] = OrderedDict()
        self._rays: np.ndarray | None = None

    # ---- geometry ----------------------------------------------------------------------------

    def _camera_to_sample_linear(self, angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
        """(origin of the camera in the sample frame, M) with d_sample = d_camera @ M."""
        o = self.calib.camera_to_sample(np.zeros((1, 3)), angle_deg)[0]
        return o, self.calib.sample_rotation(angle_deg)

    def trace(self, pixels: np.ndarray, angle_deg: float, dirs: np.ndarray | None = None) -> Trace:
        """Trace camera pixels (N, 2) (distorted pixel coordinates) at stage angle θ."""
        pixels = np.asarray(pixels, float).reshape(-1, 2)
        cam = self.calib.camera
        d_c = cam.rays(pixels) if dirs is None else dirs
        n = len(pixels)
        o_s, M = self._camera_to_sample_linear(angle_deg)
        scene = self.scene.at(angle_deg)
        mats = scene.materials
        albedo = np.array([m.albedo for m in mats] + [0.0])
        ks = np.array([m.specular for m in mats] + [0.0])
        shin = np.array([m.shininess for m in mats] + [1.0])
        depol = np.array([m.depolarization for m in mats] + [1.0])
        n_index = np.array([m.scattering.n if m.scattering else 0.0 for m in mats] + [0.0])

        d_s = d_c @ M
        origins = np.broadcast_to(o_s, d_s.shape)
        t, n_s, mat = scene.intersect(origins, d_s)
        hit = mat >= 0
        points = np.full((n, 3), np.nan)
        points[hit] = t[hit, None] * d_c[hit]
        normals = n_s @ M.T

        # projector side, computed for the hit rays only
        h = np.flatnonzero(hit)
        P = points[h]
        N = normals[h]
        to_p = self.calib.projector_centre - P
        dist_p = np.sqrt(np.einsum("ij,ij->i", to_p, to_p))
        L = to_p / dist_p[:, None]
        V = -d_c[h]
        cos_i = np.einsum("ij,ij->i", N, L)
        cos_v = np.einsum("ij,ij->i", N, V)
        facing = (cos_i > 0) & (cos_v > 0)

        uv, ok = project_points(self.calib.projector, P @ self.calib.R.T + self.calib.T)
        w_p, h_p = self.calib.projector.size
        inside = ok & (uv[:, 0] > -1.0) & (uv[:, 0] < w_p) & (uv[:, 1] > -1.0) & (uv[:, 1] < h_p)
        in_proj = facing & inside
        proj = np.full((n, 2), np.nan)
        proj[h[ok]] = uv[ok]

        # shadow rays in the sample frame, towards the projector centre
        shadow = np.zeros(len(h), bool)
        k = np.flatnonzero(in_proj)
        if k.size:
            hk = h[k]
            p_s = o_s + t[hk, None] * d_s[hk] + _SHADOW_OFFSET * n_s[hk]
            shadow[k] = scene.blocked(p_s, L[k] @ M, dist_p[k])
        lit = np.flatnonzero(in_proj & ~shadow)

        m = mat[h]
        vign = d_c[h, 2] ** 4  # natural cos^4 fall-off of the camera lens
        weight = np.zeros(n)
        weight_pol = np.zeros(n)
        entering = np.zeros(n)
        ambient = np.zeros(n)
        ambient[h] = self.ambient * albedo[m] * vign
        if lit.size:
            Hv = L[lit] + V[lit]
            Hv /= np.linalg.norm(Hv, axis=1, keepdims=True)
            cos_h = np.clip(np.einsum("ij,ij->i", N[lit], Hv), 0.0, 1.0)
            ml = m[lit]
            spec = ks[ml] * (shin[ml] + 8) / 8 * cos_h ** shin[ml]
            irr = cos_i[lit] * (self.projector_ref_mm / dist_p[lit]) ** 2 * vign[lit]
            weight[h[lit]] = (albedo[ml] + spec) * irr
            weight_pol[h[lit]] = (albedo[ml] * (1 - depol[ml]) + spec) * irr
            turbid = n_index[ml] > 0
            if turbid.any():
                entering[h[lit[turbid]]] = fresnel_transmittance(
                    cos_i[lit[turbid]], n_index[ml[turbid]]) * irr[turbid]

        def full(a):
            out = np.zeros(n, bool)
            out[h] = a
            return out

        return Trace(pixels, t, points, normals, mat, proj, full(in_proj), full(shadow),
                     weight, ambient, weight_pol, entering)

    def camera_rays(self) -> np.ndarray:
        """Unit camera rays (N, 3) of every sub-pixel sample, computed once (undistorting
        5 M samples takes seconds) chunk by chunk (bounded temporaries)."""
        if self._rays is None:
            cam = self.calib.camera
            n = cam.width * cam.height * self.ss ** 2
            rays = np.empty((n, 3))
            for s in range(0, n, _CHUNK):
                e = min(n, s + _CHUNK)
                rays[s:e] = cam.rays(subpixel_grid(cam.width, cam.height, self.ss, s, e))
            self._rays = rays
        return self._rays

    def sample_rays(self, k: np.ndarray) -> np.ndarray:
        """Unit camera rays (len(k), 3) of the sub-samples ``k`` (flat indices of the
        supersampled grid): the rows ``k`` of :meth:`camera_rays`, made for these samples
        alone when the rays are not kept (the same numbers: each ray is undistorted on its
        own). A full-resolution laser view so needs its chunk's rays, not all 120 MiB."""
        if self._rays is not None:
            return self._rays[k]
        row, col = np.divmod(np.asarray(k), self.calib.camera.width * self.ss)
        return self.calib.camera.rays(np.column_stack([(col + 0.5) / self.ss - 0.5,
                                                       (row + 0.5) / self.ss - 0.5]))

    def view(self, angle_deg: float) -> View:
        """Per-view precompute on the supersampled grid, cached by stage angle."""
        key = round(float(angle_deg), 9)
        if key in self._views:
            self._views.move_to_end(key)
            return self._views[key]
        same = self._same_at_every_angle()
        if same is not None:  # a sample symmetric about the axis: the view of another angle
            view = dataclasses.replace(same, angle_deg=key, seconds=0.0)
            self._views[key] = view
            self._forget_views()
            return view
        import time

        # room first: the oldest large view goes before this one is made, not after (a scan
        # never turns back; at full resolution each is ~0.1 GB, issue 33)
        self._forget_views(keep=self.cache_views - 1)
        t0 = time.perf_counter()
        cam = self.calib.camera
        ss = self.ss
        shape = (cam.height * ss, cam.width * ss)
        n = shape[0] * shape[1]
        rays = self.camera_rays()
        map_x = np.empty(n, np.float32)
        map_y = np.empty(n, np.float32)
        weight_dep = np.empty(n, np.float32)
        ambient = np.empty(n, np.float32)
        material = np.empty(n, np.int8)
        shadow = np.empty(n, bool)
        weight_pol = np.empty(n, np.float32)
        entering = np.empty(n, np.float32)
        turbid = self._turbid_material()
        receivers = _Receivers(cam.width, cam.height, ss) if turbid is not None else None
        for s in range(0, n, _CHUNK):
            e = min(n, s + _CHUNK)
            tr = self.trace(subpixel_grid(cam.width, cam.height, ss, s, e), key,
                            dirs=rays[s:e])
            lit = tr.weight > 0
            map_x[s:e] = np.where(lit, tr.projector[:, 0], _OUTSIDE)
            map_y[s:e] = np.where(lit, tr.projector[:, 1], _OUTSIDE)
            ambient[s:e] = tr.ambient
            material[s:e] = tr.material
            shadow[s:e] = tr.shadow
            weight_pol[s:e] = tr.weight_pol
            # the float32 total less the float32 polarized share, as the frames always used
            np.subtract(tr.weight.astype(np.float32), weight_pol[s:e], out=weight_dep[s:e])
            entering[s:e] = tr.entering
            if receivers is not None:
                receivers.add(np.arange(s, e), tr, turbid)
        view = View(key, ss, map_x.reshape(shape), map_y.reshape(shape),
                    weight_dep.reshape(shape),
                    _box(ambient.reshape(shape), ss), material.reshape(shape),
                    shadow.reshape(shape), weight_pol=weight_pol.reshape(shape))
        if turbid is not None:
            sc = self.scene.materials[turbid].scattering
            view.entering = entering.reshape(shape)
            view.subsurface = self._subsurface(key, turbid, receivers)
            mm_per_px = self.projector_ref_mm / cam.K[0, 0]
            r_total = view.subsurface.total_reflectance
            view.retained = (sc.retained * r_total, sc.retained_sigma_mm / mm_per_px)
        view.seconds = time.perf_counter() - t0
        self._views[key] = view
        self._forget_views()
        self.forget_large_rays()
        return view

    def forget_large_rays(self) -> None:
        """Forget the camera rays when the views hold more than :data:`SMALL_VIEWS_BYTES`:
        at 1280×1024, 2× supersampled, they are 120 MiB of float64 that a scan needs once a
        view (made again in ~1.2 s of CPU, the same to the bit; issue 33)."""
        if self.cached_bytes() > SMALL_VIEWS_BYTES:
            self._rays = None

    def _forget_views(self, keep: int | None = None) -> None:
        """Drop the oldest cached views beyond ``keep`` (default ``cache_views``) unless
        they are small."""
        keep = self.cache_views if keep is None else keep
        while len(self._views) > keep and self.cached_bytes() > SMALL_VIEWS_BYTES:
            self._views.popitem(last=False)

    def _same_at_every_angle(self) -> View | None:
        """A cached view that every stage angle shares, when the scene turns into itself
        (:meth:`StagedScene.turns_into_itself`: the paper's cylinder on the axis, with its
        plate) and has no turbid material (whose subsurface sources are kept in the sample
        frame); else None. Its maps are those of the angle it was made at: another angle's
        trace gives the same to the last bits of float64 (up to one float32 step where a
        rounding falls differently), and saves the 2-5 s a full-resolution view takes."""
        if not self._views or self._turbid_material() is not None:
            return None
        if not self.scene.turns_into_itself():
            return None
        return next(reversed(self._views.values()))

    def cached_bytes(self) -> int:
        """Bytes held by the cached views and camera rays."""
        rays = 0 if self._rays is None else self._rays.nbytes
        seen: set[int] = set()
        return rays + sum(_array_bytes(v, seen=seen) for v in self._views.values())

    def release(self, keep_below_bytes: int = 0) -> None:
        """Forget the cached views and camera rays (~0.2 GB at 1280×1024, 2× supersampled)
        unless together they hold less than ``keep_below_bytes``; they are made again on the
        next use."""
        if self.cached_bytes() >= keep_below_bytes:
            self._views.clear()
            self._rays = None

    def _turbid_material(self) -> int | None:
        """Index of the scene's (single) turbid material, if any."""
        ids = [i for i, m in enumerate(self.scene.materials) if m.scattering is not None]
        if len(ids) > 1:
            raise ValueError("the simulator supports one turbid material per scene")
        return ids[0] if ids else None

    def _subsurface(self, angle_deg: float, material: int, receivers: _Receivers) -> SubsurfaceView:
        """Projector-pixel sources on the turbid material and the camera receivers."""
        sc = self.scene.materials[material].scattering
        proj = self.calib.projector
        px_mm = self.projector_ref_mm / proj.K[0, 0]
        block = max(1, int(0.2 / px_mm))  # sources ≤ 0.2 mm apart (narrowest σ is 0.6 mm)
        wb, hb = proj.width // block, proj.height // block
        u = np.arange(wb) * block + (block - 1) / 2
        v = np.arange(hb) * block + (block - 1) / 2
        uu, vv = np.meshgrid(u, v)
        pix = np.column_stack([uu.ravel(), vv.ravel()])
        d_p = proj.rays(pix)
        cos_axis = d_p[:, 2]
        _, M = self._camera_to_sample_linear(angle_deg)
        centre_s = self.calib.camera_to_sample(self.calib.projector_centre[None], angle_deg)[0]
        d_s = (d_p @ self.calib.R) @ M
        t, nrm, mat = self.scene.at(angle_deg).intersect(np.broadcast_to(centre_s, d_s.shape), d_s)
        hit = np.flatnonzero(mat == material)
        d = d_s[hit]
        nn = nrm[hit]
        cos_i = np.clip(-np.einsum("ij,ij->i", d, nn), 0.0, 1.0)
        eta = 1.0 / sc.n
        cos_t = np.sqrt(np.clip(1 - eta ** 2 * (1 - cos_i ** 2), 0.0, 1.0))
        refr = eta * d + (eta * cos_i - cos_t)[:, None] * nn
        tangential = refr - np.einsum("ij,ij->i", refr, nn)[:, None] * nn
        points = centre_s + t[hit, None] * d + sc.transport_length_mm * tangential
        flux = (self.projector_ref_mm ** 2 * cos_axis[hit] ** 3 / (proj.K[0, 0] * proj.K[1, 1])
                * fresnel_transmittance(cos_i, sc.n))
        rec_pts, rec_pix, rec_w = receivers.result(self.calib, angle_deg)
        sigmas, weights, _ = gaussian_mixture(sc)
        view = SubsurfaceView(points, flux, hit, block, rec_pts, rec_pix, rec_w,
                              (self.calib.camera.height, self.calib.camera.width),
                              (sigmas, weights))
        return view

    # ---- per frame ---------------------------------------------------------------------------

    def render(self, view: View, radiance: np.ndarray | None) -> Light:
        """Relative image irradiance (H, W) float32, split by polarization, for projector
        radiance ``radiance`` (float32 (proj height, proj width), already defocused;
        ``None`` = projector dark)."""
        base = view.base
        if radiance is None:
            return Light(np.zeros_like(base), base.copy())
        # float maps on a float image: exact bilinear interpolation (checked in the tests).
        # The frame's image-sized arrays are lent (dotshell.runtime.hugepages): each fresh one is a new
        # mapping whose pages fault in and are zeroed (dotshell.runtime.process.fix_mmap_threshold),
        # ~7 000 faults and 19-30 ms of system time a full-resolution frame
        s = cv2.remap(radiance, view.map_x, view.map_y, cv2.INTER_LINEAR,
                      dst=hugepages.empty(view.map_x.shape, np.float32),
                      borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        h, w = base.shape
        # the supersampled products share one scratch array
        scratch = hugepages.empty(s.shape, np.float32) if view.ss > 1 else None

        def weighted(weight: np.ndarray) -> np.ndarray:
            """The box-average of ``s · weight`` over each pixel's sub-samples."""
            if scratch is None:
                return s * weight
            return cv2.resize(np.multiply(s, weight, out=scratch), (w, h),
                              dst=hugepages.empty((h, w), np.float32),
                              interpolation=cv2.INTER_AREA)

        pol = weighted(view.weight_pol)
        dep = weighted(view.depolarized_weight())
        dep += base
        if view.subsurface is not None:
            dep += view.subsurface.exitance(radiance)
            share, sigma_px = view.retained
            if share > 0:
                pol += share * cv2.GaussianBlur(weighted(view.entering), (0, 0), sigma_px)
        return Light(pol, dep)


@dataclass(frozen=True)
class SensorModel:
    """Camera sensor: electrons → digital numbers.

    Attributes:
        bit_depth: ADC bits (8 → uint8, 12 → uint16 with values 0..4095).
        full_well_e: saturation charge (electrons).
        read_noise_e: read noise (electrons rms).
        gain_dn_per_e: conversion gain (DN per electron).
        dark_offset_dn: black level added by the ADC (DN).
    """

    bit_depth: int
    full_well_e: float
    read_noise_e: float
    gain_dn_per_e: float
    dark_offset_dn: float

    @property
    def max_dn(self) -> int:
        return (1 << self.bit_depth) - 1

    def expected_std_dn(self, mean_e: np.ndarray | float) -> np.ndarray | float:
        """Model noise (DN rms) at a mean signal of ``mean_e`` electrons (incl. quantization)."""
        return np.sqrt(self.gain_dn_per_e ** 2 * (np.asarray(mean_e) + self.read_noise_e ** 2)
                       + 1.0 / 12.0)


#: largest skewness of a pixel's shot + read noise drawn from a normal distribution: the
#: normal has the exact mean and variance, and its CDF differs from the true one by at most
#: ~γ·φ(0)/6 ≈ 0.33 % at γ = 0.05 (Edgeworth). With 10 e- of read noise the skewness
#: λ/(λ + r²)^1.5 peaks at 0.038 (λ = 200 e-), so every unsaturated pixel is drawn normal.
NORMAL_SKEW_MAX = 0.05
#: a pixel within this many shot-noise sigmas of the full well gets the exact Poisson draw, so
#: that the clip at the full well applies to the shot noise alone, as on a sensor
_FULL_WELL_SIGMAS = 6.0


def exact_poisson_range(read_noise_e: float, skew_max: float = NORMAL_SKEW_MAX) -> tuple[float, float]:
    """The mean signals (electrons) ``[lo, hi)`` where shot + read noise is too skewed for a
    normal draw: where ``λ / (λ + r²)^1.5 > skew_max``. Empty (``lo == hi``) when the read
    noise ``r`` (e- rms) keeps the skewness below ``skew_max`` everywhere."""
    r2 = float(read_noise_e) ** 2

    def skew(lam: float) -> float:
        return lam / (lam + r2) ** 1.5 if lam + r2 > 0 else math.inf

    peak = 2.0 * r2  # the skewness rises up to λ = 2 r², then falls
    if skew(peak) <= skew_max:
        return 0.0, 0.0

    def crossing(a: float, b: float, rising: bool) -> float:
        for _ in range(200):
            m = 0.5 * (a + b)
            if (skew(m) > skew_max) == rising:
                b = m
            else:
                a = m
        return b

    lo = 0.0 if r2 == 0 or skew(0.0) > skew_max else crossing(0.0, peak, True)
    hi_end = max(peak, 1.0)
    while skew(hi_end) > skew_max:
        hi_end *= 2.0
    return lo, crossing(peak, hi_end, False)


def _exact_pixels(lam: np.ndarray, model: SensorModel) -> np.ndarray:
    """Flat indices of the pixels whose noise is drawn exactly (Poisson, then the clip at the
    full well, then read noise): too skewed for a normal draw, or near the full well."""
    lo, hi = exact_poisson_range(model.read_noise_e)
    fw = model.full_well_e
    near_full = fw - _FULL_WELL_SIGMAS * math.sqrt(fw)
    exact = np.greater(lam, np.float32(near_full), out=hugepages.empty(lam.shape, bool))
    if hi > lo:
        exact |= (lam >= np.float32(lo)) & (lam < np.float32(hi))
    return np.flatnonzero(exact)


def sensor(electrons: np.ndarray, model: SensorModel, rng: np.random.Generator) -> np.ndarray:
    """Shot noise, full-well clipping, read noise, offset, ADC rounding and clipping.

    Shot plus read noise of a mean of λ electrons is Poisson(λ) + N(0, r²). Where that sum is
    nearly symmetric (skewness ≤ :data:`NORMAL_SKEW_MAX`) and far from the full well it is
    drawn as one normal N(λ, λ + r²) (exact mean and variance; ~5× faster than numpy's Poisson
    draw, which took ~3/4 of a frame's CPU); elsewhere exactly: Poisson, clipped at the full
    well, plus read noise."""
    lam = np.maximum(electrons, 0.0, out=hugepages.empty(electrons.shape, np.float32))
    e = rng.standard_normal(lam.shape, dtype=np.float32, out=hugepages.empty(lam.shape,
                                                                           np.float32))
    std = np.add(lam, np.float32(model.read_noise_e ** 2), out=hugepages.empty(lam.shape,
                                                                               np.float32))
    np.sqrt(std, out=std)
    e *= std
    e += lam
    idx = _exact_pixels(lam, model)
    if idx.size:
        shot = rng.poisson(lam.reshape(-1)[idx]).astype(np.float32)
        np.minimum(shot, model.full_well_e, out=shot)
        if model.read_noise_e > 0:
            shot += rng.standard_normal(idx.size, dtype=np.float32) * np.float32(model.read_noise_e)
        e.reshape(-1)[idx] = shot
    dn = e
    dn *= np.float32(model.gain_dn_per_e)
    dn += np.float32(model.dark_offset_dn)
    np.rint(dn, out=dn)
    np.clip(dn, 0, model.max_dn, out=dn)
    return dn.astype(np.uint8 if model.bit_depth <= 8 else np.uint16)
