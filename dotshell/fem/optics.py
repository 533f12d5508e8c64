"""Light leaving a diffusive sample through its surface: Fresnel transmission and the angular
distribution of the exiting radiance in diffusion theory. Shared by the simulator (which renders
trans-illumination images with it) and the ``diffuse-fresnel`` normalizer (which undoes it).

Inside a diffusive medium near its boundary the radiance is, to first order in the diffusion
approximation, ``L_in(ŝ) = φ/(4π) + 3/(4π) · J·ŝ``. With the Robin boundary condition of
:mod:`dotshell.fem.forward` the outward flux is ``J_n = φ / (2A)``. Light heading outwards at the
internal angle θi crosses the surface with the Fresnel transmittance ``T(θi)`` (unpolarized,
refractive index ``n`` inside, air outside) and leaves at ``sin θo = n sin θi``; radiance divided
by n² is conserved across the interface. The radiance seen from outside at exit angle θo is
therefore::

    L(θo) = φ / (4π n²) · T(θi) · (1 + 3 cos θi / (2A))

It falls towards grazing exit because T(θi) → 0 as θi approaches the critical angle; a
Lambertian emitter (constant L) is the special case n = 1 without the flux term. References:
Haskell et al., J. Opt. Soc. Am. A 11, 2727 (1994) (partial-current boundary, exiting
radiance); Ripoll et al., Opt. Lett. 28, 1701 (2003) (non-contact imaging of the exiting
light). Angles in radians or as cosines, as named; lengths in mm.
"""

from __future__ import annotations

import math

import numpy as np


def fresnel_transmittance_out(cos_inside: np.ndarray, n: float) -> np.ndarray:
    """Unpolarized Fresnel transmittance from the medium (index ``n``) into air for light
    meeting the surface at internal angle θi (given as cos θi ≥ 0). Zero beyond the critical
    angle (total internal reflection)."""
    ci = np.clip(np.asarray(cos_inside, float), 0.0, 1.0)
    si = np.sqrt(1.0 - ci * ci)
    so = n * si
    ok = so < 1.0
    co = np.sqrt(np.clip(1.0 - so * so, 0.0, 1.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        rs = ((n * ci - co) / (n * ci + co)) ** 2
        rp = ((n * co - ci) / (n * co + ci)) ** 2
    t = 1.0 - 0.5 * (rs + rp)
    return np.where(ok, np.nan_to_num(t, nan=0.0), 0.0)


def cos_inside(cos_outside: np.ndarray | float, n: float) -> np.ndarray:
    """cos θi of the internal ray that leaves at exit angle θo (cos θo given, Snell's law)."""
    co = np.clip(np.asarray(cos_outside, float), 0.0, 1.0)
    so = np.sqrt(1.0 - co * co)
    return np.sqrt(np.clip(1.0 - (so / n) ** 2, 0.0, 1.0))


def exit_radiance_per_fluence(cos_outside: np.ndarray | float, n: float) -> np.ndarray:
    """Exiting radiance L(θo) per unit fluence φ just inside the surface (1/sr), for exit
    directions with cos θo = ``cos_outside`` measured from the outward normal."""
    from dotshell.fem.forward import robin_A  # here: the FEM module loads scipy.sparse

    ci = cos_inside(cos_outside, n)
    A = robin_A(n)
    return fresnel_transmittance_out(ci, n) * (1.0 + 1.5 * ci / A) / (4.0 * math.pi * n * n)


def exit_radiance_factor(cos_outside: np.ndarray, n: float) -> np.ndarray:
    """``L(θo) / L(0)``: how much dimmer the surface looks at exit angle θo than seen along its
    normal (1 at normal exit, → 0 at grazing exit)."""
    return exit_radiance_per_fluence(cos_outside, n) / float(exit_radiance_per_fluence(1.0, n))
