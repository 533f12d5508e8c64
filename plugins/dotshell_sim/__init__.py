"""dotshell_sim — a simulated structured-light rig (camera, projector, turntable, analyzer, laser).

Registered under the ``dotshell`` entry-point group as ``sim = "dotshell_sim"``. The devices of
one rig share a world in ``context.shared["dotshell_sim"]``; the camera renders it by exact ray
casting (see :mod:`dotshell_sim.render`, :mod:`dotshell_sim.scene`). Defaults describe the
reference bench of ``profiles/sim-metal-cylinder.toml``; :func:`dotshell_sim.bench.scale_profile`
shrinks it for fast tests.

Its backends are declared in ``dotshell.toml`` and built in :mod:`dotshell_sim.backends`: this
module imports none of the simulator (the names below are imported on first access).
"""

from __future__ import annotations

from dotshell import hookimpl
from dotshell.backends import Backend
from dotshell.manifest import backends_of, lazy_exports

__all__ = ["SimAnalyzer", "SimCamera", "SimLaser", "SimProjector", "SimTurntable", "SimWorld",
           "world_of"]
__getattr__ = lazy_exports(__name__, {name: f"devices:{name}" for name in __all__})


# The hooks below serve when this package is registered as a plain pluggy plugin; the plugin
# manager reads dotshell.toml instead and imports a backend only when it is used.

@hookimpl
def dotshell_cameras() -> list[Backend]:
    return backends_of(__name__, "camera")


@hookimpl
def dotshell_projectors() -> list[Backend]:
    return backends_of(__name__, "projector")


@hookimpl
def dotshell_stages() -> list[Backend]:
    return backends_of(__name__, "stage")


@hookimpl
def dotshell_analyzers() -> list[Backend]:
    return backends_of(__name__, "analyzer")


@hookimpl
def dotshell_light_sources() -> list[Backend]:
    return backends_of(__name__, "light_source")
