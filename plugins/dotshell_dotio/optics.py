"""Per-node optical properties of a volume mesh as the DOT formats write them (NIRFAST
``.param``/``.region``, TOAST ``[ParameterList]``): one place for the values a mesh without
them gets, which are the profile's ``[mesh.optics]`` defaults."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dotshell.fem.meshes import TetMesh
from dotshell.fem.meshfiles import OPTICS
from dotshell.profile.mesh import MESH_SCHEMA

#: μa (1/mm), μs' (1/mm) and n for a mesh whose ``volume.vtu`` carries none: the ``[mesh.optics]``
#: defaults, so an exported file and a meshed run agree.
DEFAULT_OPTICS: dict[str, float] = {
    name: (MESH_SCHEMA["optics"].schema or {})[name].default for name in OPTICS}


def kappa_mm(mua_per_mm: np.ndarray, musp_per_mm: np.ndarray) -> np.ndarray:
    """Diffusion coefficient κ = 1 / (3 (μa + μs')) in mm."""
    return 1.0 / (3.0 * (np.asarray(mua_per_mm) + np.asarray(musp_per_mm)))


@dataclass
class NodeOptics:
    """One value per node: μa (1/mm), μs' (1/mm), refractive index and 1-based region."""

    mua_per_mm: np.ndarray
    musp_per_mm: np.ndarray
    refractive_index: np.ndarray
    region: np.ndarray

    @property
    def kappa_mm(self) -> np.ndarray:
        """Diffusion coefficient per node (mm)."""
        return kappa_mm(self.mua_per_mm, self.musp_per_mm)


def node_optics(mesh: TetMesh) -> NodeOptics:
    """The mesh's per-node properties, :data:`DEFAULT_OPTICS` (and region 1) where absent."""
    n = len(mesh.nodes)
    pd = mesh.point_data
    values = {name: pd.get(name, np.full(n, DEFAULT_OPTICS[name])) for name in OPTICS}
    return NodeOptics(**values, region=pd.get("region", np.ones(n)))
