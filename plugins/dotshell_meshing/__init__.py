"""dotshell_meshing — first-party surface and volume meshers.

Registered under the ``dotshell`` entry-point group as ``meshing = "dotshell_meshing"``:

* surface mesher ``open3d-poisson`` (:mod:`dotshell_meshing.surface`): outlier removal, voxel
  down-sampling, outward normals, Poisson reconstruction with density trimming, the open bottom
  closed at the plate plane, uniform remeshing to the node distance, repair to a closed
  manifold;
* volume mesher ``tetgen`` (:mod:`dotshell_meshing.volume`): quality tetrahedra with a maximum
  element volume set by the node distance.

Both implement the protocols of :mod:`dotshell.fem.meshes`; factories take ``(settings, context)``
with ``context=None`` (no hardware). They are declared in ``dotshell.toml`` and built in
:mod:`dotshell_meshing.backends`: this module imports no mesher.
"""

from __future__ import annotations

from dotshell import hookimpl
from dotshell.backends import Backend
from dotshell.manifest import backends_of


@hookimpl
def dotshell_surface_meshers() -> list[Backend]:
    return backends_of(__name__, "surface_mesher")


@hookimpl
def dotshell_volume_meshers() -> list[Backend]:
    return backends_of(__name__, "volume_mesher")
