"""The normalization methods of :mod:`dotshell_normalizers` (orientation factors of sin β)."""

from __future__ import annotations

import numpy as np

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


def none() -> Backend:
    return Backend("none", lambda settings=None, context=None: NoNormalization(), {})


def lambertian() -> Backend:
    return Backend("lambertian", lambda settings=None, context=None: LambertianNormalization(), {})


def diffuse_fresnel() -> Backend:
    return Backend("diffuse-fresnel", lambda settings, context=None: DiffuseFresnelNormalization(
        settings["refractive_index"]), FRESNEL_SETTINGS)
