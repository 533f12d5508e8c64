"""dotshell_normalizers — first-party intensity normalizers for trans-illumination images.

Registered under the ``dotshell`` entry-point group as ``normalizers = "dotshell_normalizers"``.
Each backend implements :class:`dotshell.normalizer.Normalizer`:

* ``none`` — no correction (factor 1): the raw node intensities, for comparison;
* ``lambertian`` — the paper's Eq. 1, a Lambertian emitter per node: factor sin β;
* ``diffuse-fresnel`` — light leaving a diffusive medium of refractive index n through its
  surface (Fresnel transmission and the diffusion-theory flux term, :mod:`dotshell.fem.optics`):
  factor sin β · L(θo)/L(0) with cos θo = sin β. Falls to the Lambertian model for n → 1 only
  in the Fresnel part; at the default grazing limit (sin β = 0.3) it differs from it by 25 %.
"""

from __future__ import annotations

import numpy as np

from dotshell import hookimpl
from dotshell.backends import Backend
from dotshell.fem.optics import exit_radiance_factor
from dotshell.settings import Setting


class NoNormalization:
    def orientation_factor(self, sin_beta: np.ndarray) -> np.ndarray:
        return np.ones_like(np.asarray(sin_beta, float))


class LambertianNormalization:
    def orientation_factor(self, sin_beta: np.ndarray) -> np.ndarray:
        return np.asarray(sin_beta, float)


class DiffuseFresnelNormalization:
    def __init__(self, refractive_index: float) -> None:
        self.n = refractive_index

    def orientation_factor(self, sin_beta: np.ndarray) -> np.ndarray:
        s = np.asarray(sin_beta, float)
        return s * exit_radiance_factor(s, self.n)


FRESNEL_SETTINGS = {
    "refractive_index": Setting("float", default=0.0, min=0.0,
                                help="refractive index n of the sample; 0 = take [mesh.optics] "
                                     "refractive_index"),
}


@hookimpl
def dotshell_normalizers() -> list[Backend]:
    return [
        Backend("none", lambda settings=None, context=None: NoNormalization(), {},
                "no orientation correction (the raw node intensities)"),
        Backend("lambertian", lambda settings=None, context=None: LambertianNormalization(), {},
                "the paper's Eq. 1: Lambertian emitter per node, I = I0 · sin β"),
        Backend("diffuse-fresnel",
                lambda settings, context=None: DiffuseFresnelNormalization(
                    settings["refractive_index"]),
                FRESNEL_SETTINGS,
                "diffusion theory + Fresnel transmission at refractive index n "
                "(dotshell.fem.optics): I = I0 · sin β · L(θ)/L(0)"),
    ]
