"""The normalizer role: how a surface element's orientation to the camera scales the light the
camera receives from it.

The quantity dotshell measures per surface node k is the **node intensity** ``I_k``: the power
the node's surface element sends towards the camera per unit of its area and per unit solid
angle (flat-fielded camera DN per ms; see docs/transillumination.md). The paper's Eq. 1 relates
it to the intensity ``I0_k`` the element emits along its own normal: ``I_k = I0_k · sin β_k``
for a Lambertian emitter, β_k the angle between the view direction and the surface element (so
sin β_k is the cosine between the outward normal and the direction from the node to the camera
centre). A normalizer backend returns that ratio ``I_k / I0_k`` as a function of sin β; the core
divides by it. Backends are created with ``factory(settings, context=None)``.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Normalizer(Protocol):
    def orientation_factor(self, sin_beta: np.ndarray) -> np.ndarray:
        """``I_k / I0_k`` for nodes seen at ``sin_beta`` (0 < sin β ≤ 1), same shape."""
        ...
