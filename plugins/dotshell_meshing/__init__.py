"""dotshell_meshing — first-party surface and volume meshers.

Registered under the ``dotshell`` entry-point group as ``meshing = "dotshell_meshing"``:

* surface mesher ``open3d-poisson`` (:mod:`dotshell_meshing.surface`): outlier removal, voxel
  down-sampling, outward normals, Poisson reconstruction with density trimming, the open bottom
  closed at the plate plane, uniform remeshing to the node distance, repair to a closed
  manifold;
* volume mesher ``tetgen`` (:mod:`dotshell_meshing.volume`): quality tetrahedra with a maximum
  element volume set by the node distance.

Both implement the protocols of :mod:`dotshell.fem.meshes`; factories take ``(settings, context)``
with ``context=None`` (no hardware).
"""

from __future__ import annotations

from dotshell import hookimpl
from dotshell.backends import Backend

from dotshell_meshing import surface, volume


@hookimpl
def dotshell_surface_meshers() -> list[Backend]:
    return [Backend("open3d-poisson",
                    lambda settings, context=None: surface.PoissonSurfaceMesher(settings),
                    surface.SETTINGS,
                    "cloud → closed surface: outliers, voxels, outward normals, Poisson, "
                    "bottom closed at the plate, uniform remesh (pyacvd), repair (pymeshfix)")]


@hookimpl
def dotshell_volume_meshers() -> list[Backend]:
    return [Backend("tetgen", lambda settings, context=None: volume.TetgenVolumeMesher(settings),
                    volume.SETTINGS,
                    "closed surface → quality tetrahedra (TetGen), max volume from the node "
                    "distance")]
