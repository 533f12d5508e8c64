"""Volume mesher ``tetgen``: closed surface → quality tetrahedral mesh (TetGen through the PyPI
``tetgen`` wrapper).

The maximum element volume is a multiple (``volume_scale``, 1.6) of that of a regular
tetrahedron with edge = the node distance, ``d³ / (6√2)``: TetGen's elements come out smaller
than the bound, and 1.6 gives a median edge length of about ``d`` (measured). TetGen's quality refinement bounds
the radius–edge ratio and the minimum dihedral angle. Elements come back positively oriented
and nodes no element uses are dropped.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from dotshell.fem.faces import unshared_faces
from dotshell.fem.meshes import (MeshError, TetMesh, TriangleSurface, closed_manifold_problems,
                          compact, joe_liu_quality, orient_positive)
from dotshell.settings import Setting

SETTINGS: dict[str, Setting] = {
    "radius_edge_ratio": Setting("float", 1.5, "TetGen quality bound: largest circumradius / "
                                 "shortest edge of an element", min=1.05),
    "min_dihedral_deg": Setting("float", 15.0, "TetGen quality bound: smallest dihedral angle "
                                "it tries to reach", "deg", min=0.0, max=30.0),
    "max_dihedral_deg": Setting("float", 165.0, "TetGen optimisation: flip and smooth elements "
                                "with a larger dihedral angle (removes boundary slivers)", "deg",
                                min=90.0, max=180.0),
    "optimize_iterations": Setting("int", 10, "TetGen mesh optimisation passes", min=0, max=100),
    "volume_scale": Setting("float", 1.6, "maximum element volume as a multiple of d³/(6√2), "
                            "the volume of a regular tetrahedron with edge d; 1.6 gives a median "
                            "edge of about d", min=0.01),
}


def max_element_volume_mm3(node_distance_mm: float) -> float:
    """Volume of a regular tetrahedron whose edges are ``node_distance_mm`` long."""
    return node_distance_mm ** 3 / (6.0 * math.sqrt(2.0))


class TetgenVolumeMesher:
    """Implements :class:`dotshell.fem.meshes.VolumeMesher` with TetGen."""

    def __init__(self, settings: dict[str, Any]):
        self.s = settings

    def volume(self, surface: TriangleSurface, node_distance_mm: float) -> TetMesh:
        if not (math.isfinite(node_distance_mm) and node_distance_mm > 0):
            raise MeshError(f"node distance must be a positive number of mm, got "
                            f"{node_distance_mm!r}; set [mesh] node_distance_mm.")
        problems = closed_manifold_problems(surface)
        if problems:
            raise MeshError("the volume mesher needs a closed, outward-oriented surface; this "
                            "one has " + "; ".join(problems) + ". Re-run the surface step or "
                            "repair the surface first.")
        import tetgen

        tg = tetgen.TetGen(surface.vertices, surface.triangles.astype(np.int32))
        vmax = max_element_volume_mm3(node_distance_mm) * self.s["volume_scale"]
        try:
            nodes, tets, *_ = tg.tetrahedralize(
                quality=True, minratio=self.s["radius_edge_ratio"],
                mindihedral=self.s["min_dihedral_deg"], fixedvolume=True, maxvolume=vmax,
                optmaxdihedral=self.s["max_dihedral_deg"], opt_max_flip_level=5,
                opt_iterations=self.s["optimize_iterations"], quiet=True, nowarning=True)
        except RuntimeError as exc:
            raise MeshError(f"TetGen could not fill the surface ({exc}); the surface may "
                            "self-intersect. Try a larger node distance.") from None
        nodes = np.asarray(nodes)
        tets = peel_boundary_slivers(nodes, orient_positive(nodes, np.asarray(tets)[:, :4]))
        return compact(nodes, tets)


def peel_boundary_slivers(nodes: np.ndarray, tets: np.ndarray, min_quality: float = 0.05,
                          rounds: int = 5) -> np.ndarray:
    """Remove near-flat elements (Joe–Liu quality below ``min_quality``) that lie on the
    surface with two or more faces: TetGen keeps them when four surface nodes are almost
    coplanar (e.g. on the flat bottom next to a narrow gap). Removing one changes the enclosed
    volume by its own, near-zero volume and leaves a closed boundary."""
    for _ in range(rounds):
        # the quality of the elements with two or more faces on the surface alone (the demo's
        # 62 k tetrahedra: 63 -> 30 ms a round, the same elements dropped)
        candidates = np.flatnonzero(unshared_faces(tets).sum(axis=1) >= 2)
        drop = candidates[joe_liu_quality(nodes, tets[candidates]) < min_quality]
        if not len(drop):
            break
        tets = np.delete(tets, drop, axis=0)
    return tets
