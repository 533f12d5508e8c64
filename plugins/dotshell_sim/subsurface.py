"""Subsurface light transport for semi-transparent materials (agar, tissue, gummy bears).

Light entering a turbid medium is re-emitted around its entry point after many scattering
events. We use the standard diffusion dipole (Farrell, Patterson & Wilson, Med. Phys. 19, 1992;
Jensen et al., SIGGRAPH 2001) for the radial exit profile R_d(r) [1/mm²] of a pencil beam,
fitted by a non-negative sum of 2-D Gaussians so it can be applied as separable 3-D blurs:

* **sources**: every projector pixel's ray is traced to its first surface hit; the flux it
  carries into the medium (Fresnel transmission at refractive index n) is deposited at the entry
  point displaced along the surface by one transport length along the *refracted* ray (the
  dipole's source sits at depth z0 = 1/μt' on the refracted ray; for oblique light it lands
  beside the entry point — this is what shifts stripe edges on curved translucent samples);
* **transport**: per Gaussian component, the sources are binned into a voxel grid (sample
  frame, voxel ≈ σ/2.5), blurred with a normalized 3-D Gaussian and read back by trilinear
  interpolation at the surface points the camera sees. For a source sheet, a 3-D Gaussian read
  on the sheet equals the 2-D Gaussian × 1/(√(2π)σ), which the weights undo;
* **polarization**: the diffusely re-emitted light is depolarized. A small ``retained`` share,
  re-emitted within ``retained_sigma_mm`` of the entry point after few scattering events, keeps
  the projector's polarization (so polarization difference imaging is not perfect); it is applied
  in camera-image space (the surface is flat at that scale).

Units: mm, 1/mm. Radiometry in the renderer's relative units (1 = white Lambertian facing the
projector at its reference distance).
"""

from __future__ import annotations

import hashlib
import math
from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class Scattering:
    """Optical properties of a turbid material.

    Attributes:
        mus_prime_per_mm: reduced scattering coefficient μs' (1/mm).
        mua_per_mm: absorption coefficient μa (1/mm).
        n: refractive index (the surroundings are air, n = 1).
        retained: share of the diffuse light that keeps its polarization (0..1).
        retained_sigma_mm: spread of that share around the entry point (mm).
    """

    mus_prime_per_mm: float
    mua_per_mm: float
    n: float
    retained: float = 0.04
    retained_sigma_mm: float = 0.3

    @property
    def mut_prime(self) -> float:
        return self.mus_prime_per_mm + self.mua_per_mm

    @property
    def transport_length_mm(self) -> float:
        """1/μt' (mm): depth of the dipole's real source."""
        return 1.0 / self.mut_prime

    @property
    def mu_eff(self) -> float:
        """Effective attenuation sqrt(3 μa μt') (1/mm)."""
        return math.sqrt(3 * self.mua_per_mm * self.mut_prime)


def internal_reflection_A(n: float) -> float:
    """Boundary mismatch factor A = (1 + F_dr)/(1 − F_dr), F_dr from Egan & Hilgeman's fit."""
    f_dr = -1.440 / n ** 2 + 0.710 / n + 0.668 + 0.0636 * n
    return (1 + f_dr) / (1 - f_dr)


def dipole_profile(r_mm: np.ndarray, s: Scattering) -> np.ndarray:
    """Diffuse reflectance R_d(r) (1/mm²) at distance r from a normally incident pencil beam."""
    r = np.asarray(r_mm, float)
    alpha = s.mus_prime_per_mm / s.mut_prime
    z0 = 1.0 / s.mut_prime
    zv = z0 + 4 * internal_reflection_A(s.n) / (3 * s.mut_prime)
    r1 = np.sqrt(r * r + z0 * z0)
    r2 = np.sqrt(r * r + zv * zv)
    mu = s.mu_eff
    return alpha / (4 * np.pi) * (z0 * (mu + 1 / r1) * np.exp(-mu * r1) / r1 ** 2
                                  + zv * (mu + 1 / r2) * np.exp(-mu * r2) / r2 ** 2)


def fresnel_transmittance(cos_i: np.ndarray, n: float) -> np.ndarray:
    """Unpolarized Fresnel transmittance from air into a medium of index n."""
    ci = np.clip(np.asarray(cos_i, float), 1e-6, 1.0)
    st = np.sqrt(1 - ci * ci) / n
    ct = np.sqrt(np.clip(1 - st * st, 0, 1))
    rs = ((ci - n * ct) / (ci + n * ct)) ** 2
    rp = ((n * ci - ct) / (n * ci + ct)) ** 2
    return 1 - 0.5 * (rs + rp)


def gaussian_mixture(s: Scattering, sigmas_mm=(0.6, 1.2, 2.4, 4.8, 9.6),
                     r_max_mm: float = 60.0) -> tuple[np.ndarray, np.ndarray, float]:
    """Fit R_d(r) by Σ w_c·G2(r; σ_c) with w_c ≥ 0 (least squares on the ring integrand 2πr·R_d).

    Returns (sigmas_mm, weights, relative L2 error of the fit). Σ weights ≈ total diffuse
    reflectance."""
    from scipy.optimize import nnls  # here: scipy is for scattering samples only (0.5 s to load)

    r = np.linspace(1e-3, r_max_mm, 4000)
    target = 2 * np.pi * r * dipole_profile(r, s)
    sig = np.asarray(sigmas_mm, float)
    basis = np.stack([2 * np.pi * r * np.exp(-r ** 2 / (2 * c * c)) / (2 * np.pi * c * c)
                      for c in sig], axis=1)
    w, _ = nnls(basis, target)
    err = float(np.linalg.norm(basis @ w - target) / np.linalg.norm(target))
    keep = w > 1e-6 * w.sum()
    return sig[keep], w[keep], err


@dataclass
class _Component:
    sigma_mm: float
    weight: float
    voxel_mm: float
    shape: tuple[int, int, int]
    source_index: np.ndarray      # linear voxel index per source
    receiver_corner: np.ndarray   # (R,) linear index of the voxel below each receiver
    receiver_frac: np.ndarray     # (3, R) float32 position within that voxel (0..1 per axis)

    def read(self, grid: np.ndarray) -> np.ndarray:
        """Trilinear interpolation of ``grid`` (of this component's shape) at the receivers
        (``map_coordinates(order=1)``; the receivers lie inside the grid by construction)."""
        g = grid.ravel()
        s0, s1 = self.shape[1] * self.shape[2], self.shape[2]
        f0, f1, f2 = self.receiver_frac
        out = np.zeros(len(self.receiver_corner), np.float32)
        for d0, w0 in ((0, 1 - f0), (s0, f0)):
            for d1, w1 in ((0, 1 - f1), (s1, f1)):
                w01 = w0 * w1
                i = self.receiver_corner + (d0 + d1)
                out += w01 * (g[i] * (1 - f2) + g[i + 1] * f2)
        return out


#: Bytes of exitance images a view keeps, by projector radiance: a PDI scan renders every pattern
#: twice (analyzer parallel, then crossed) and the depolarized light does not depend on the
#: analyzer. 32 MiB holds a reduced-resolution view's whole pattern set (a 320x256 image is
#: 0.3 MiB; measured: the 0.25x agar PDI scan of tests/test_pdi.py renders in 40 % less time);
#: at full resolution (5 MiB an image) the pairs are farther apart than it holds.
EXITANCE_CACHE_BYTES = 32 << 20


class SubsurfaceView:
    """Per-view precompute: projector sources and camera receivers on one turbid material.

    Args:
        source_points: (S, 3) displaced source positions, sample frame (mm).
        source_flux: (S,) flux factor per source (relative units per unit projector radiance).
        source_pixels: (S,) linear index into the (block-downsampled) projector radiance image.
        block: projector pixels per source along each axis.
        receiver_points: (R, 3) surface points seen by the camera pixels, sample frame (mm).
        receiver_pixels: (R,) linear camera-pixel index of each receiver.
        receiver_weight: (R,) share of the pixel on this material × camera vignetting.
        image_shape: camera (H, W).
        mixture: (sigmas_mm, weights) of the diffuse profile.
    """

    def __init__(self, source_points, source_flux, source_pixels, block, receiver_points,
                 receiver_pixels, receiver_weight, image_shape, mixture) -> None:
        self.source_flux = np.asarray(source_flux, np.float64)
        self.source_pixels = np.asarray(source_pixels, np.int64)
        self.block = int(block)
        self.receiver_pixels = np.asarray(receiver_pixels, np.int64)
        self.receiver_weight = np.asarray(receiver_weight, np.float32)
        self.image_shape = image_shape
        self.total_reflectance = float(np.sum(mixture[1]))
        pts = np.vstack([source_points, receiver_points]) if len(receiver_points) else source_points
        lo = pts.min(axis=0) - 0.5
        hi = pts.max(axis=0) + 0.5
        self.components = []
        for sigma, weight in zip(*mixture):
            vox = float(np.clip(sigma / 2.5, 0.1, 2.0))
            shape = tuple(int(v) for v in np.ceil((hi - lo) / vox).astype(int) + 2)
            si = np.clip(np.round((source_points - lo) / vox).astype(int), 0, np.array(shape) - 1)
            lin = np.ravel_multi_index(si.T, shape)
            rc = (np.asarray(receiver_points, float).reshape(-1, 3) - lo) / vox
            corner = np.clip(np.floor(rc).astype(np.int64), 0, np.array(shape) - 2)
            frac = (rc - corner).T.astype(np.float32)
            # int32 voxel indices where the grid allows: 4 bytes less per receiver and
            # component, ~14 MB of a full-resolution agar view (issue 33), the same voxels
            index = np.int32 if math.prod(shape) < np.iinfo(np.int32).max else np.int64
            self.components.append(_Component(float(sigma), float(weight), vox, shape, lin,
                                              np.ravel_multi_index(corner.T, shape).astype(index),
                                              frac))
        self._exitances: OrderedDict[bytes, np.ndarray] = OrderedDict()

    def exitance(self, radiance: np.ndarray) -> np.ndarray:
        """Depolarized exit radiance (H, W) float32 (read-only) for projector radiance (h, w)
        float32; the same radiance again gives the kept image (:data:`EXITANCE_CACHE_BYTES`)."""
        radiance = np.ascontiguousarray(radiance)
        key = hashlib.blake2b(memoryview(radiance).cast("B"), digest_size=16,
                              person=str(radiance.shape).encode()[:16]).digest()
        out = self._exitances.get(key)
        if out is None:
            out = self._exitance(radiance)
            out.flags.writeable = False
            self._exitances[key] = out
            while len(self._exitances) * out.nbytes > EXITANCE_CACHE_BYTES:
                self._exitances.popitem(last=False)
        else:
            self._exitances.move_to_end(key)
        return out

    def _exitance(self, radiance: np.ndarray) -> np.ndarray:
        h, w = radiance.shape
        b = self.block
        if b > 1:
            hb, wb = h // b, w // b
            radiance = radiance[:hb * b, :wb * b].reshape(hb, b, wb, b).sum(axis=(1, 3))
        flux = radiance.ravel()[self.source_pixels] * self.source_flux
        total = np.zeros(len(self.receiver_pixels))
        for c in self.components:
            grid = np.bincount(c.source_index, weights=flux, minlength=int(np.prod(c.shape)))
            grid = gaussian_blur_3d((grid / c.voxel_mm ** 3).astype(np.float32).reshape(c.shape),
                                    c.sigma_mm / c.voxel_mm)
            total += c.weight * math.sqrt(2 * math.pi) * c.sigma_mm * c.read(grid)
        out = np.zeros(self.image_shape[0] * self.image_shape[1], np.float32)
        np.add.at(out, self.receiver_pixels, (total * self.receiver_weight).astype(np.float32))
        return out.reshape(self.image_shape)


def gaussian_blur_3d(grid: np.ndarray, sigma_voxels: float, truncate: float = 3.5) -> np.ndarray:
    """Normalized 3-D Gaussian blur of a float32 voxel grid (zeros outside), σ in voxels, the
    kernel cut at ``truncate``·σ: ``scipy.ndimage.gaussian_filter(mode="constant")``'s result
    to float32 precision, as three 1-D passes of OpenCV's separable filter (about 3x less CPU
    than scipy's float64 filter on the 1.8 M-voxel grids of a reduced agar view). Blurs
    ``grid`` in place and returns it."""
    radius = int(truncate * sigma_voxels + 0.5)
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / sigma_voxels) ** 2)
    k = (k / k.sum()).astype(np.float32)
    one = np.ones(1, np.float32)
    n0, n1, n2 = grid.shape
    border = cv2.BORDER_CONSTANT
    # last axis: rows of (n0·n1, n2); first axis: columns of (n0, n1·n2); middle: slice by slice
    grid[...] = cv2.sepFilter2D(grid.reshape(n0 * n1, n2), -1, k, one,
                                borderType=border).reshape(grid.shape)
    grid[...] = cv2.sepFilter2D(grid.reshape(n0, n1 * n2), -1, one, k,
                                borderType=border).reshape(grid.shape)
    for i in range(n0):
        grid[i] = cv2.sepFilter2D(grid[i], -1, one, k, borderType=border)
    return grid
