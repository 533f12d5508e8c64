"""dotshell_normalizers — first-party intensity normalizers for trans-illumination images.

Registered under the ``dotshell`` entry-point group as ``normalizers = "dotshell_normalizers"``.
Each backend implements :class:`dotshell.normalizer.Normalizer`:

* ``none`` — no correction (factor 1): the raw node intensities, for comparison;
* ``lambertian`` — the paper's Eq. 1, a Lambertian emitter per node: factor sin β;
* ``diffuse-fresnel`` — light leaving a diffusive medium of refractive index n through its
  surface (Fresnel transmission and the diffusion-theory flux term, :mod:`dotshell.fem.optics`):
  factor sin β · L(θo)/L(0) with cos θo = sin β. Falls to the Lambertian model for n → 1 only
  in the Fresnel part; at the default grazing limit (sin β = 0.3) it differs from it by 25 %.

The backends are declared in ``dotshell.toml`` and built in :mod:`dotshell_normalizers.methods`
(imported on first use, as are the names below).
"""

from __future__ import annotations

from dotshell import hookimpl
from dotshell.backends import Backend
from dotshell.manifest import backends_of, lazy_exports

__all__ = ["NoNormalization", "LambertianNormalization", "DiffuseFresnelNormalization",
           "FRESNEL_SETTINGS"]
__getattr__ = lazy_exports(__name__, {name: f"methods:{name}" for name in __all__})


@hookimpl
def dotshell_normalizers() -> list[Backend]:
    """All normalizers (when this package is registered as a plain pluggy plugin)."""
    return backends_of(__name__, "normalizer")
