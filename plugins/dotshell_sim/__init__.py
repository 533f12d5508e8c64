"""dotshell_sim — a simulated structured-light rig (camera, projector, turntable, analyzer, laser).

Registered under the ``dotshell`` entry-point group as ``sim = "dotshell_sim"``. The devices of
one rig share a world in ``context.shared["dotshell_sim"]``; the camera renders it by exact ray
casting (see :mod:`dotshell_sim.render`, :mod:`dotshell_sim.scene`). Defaults describe the
reference bench of ``profiles/sim-metal-cylinder.toml``; :func:`dotshell_sim.bench.scale_profile`
shrinks it for fast tests.
"""

from __future__ import annotations

from dotshell import hookimpl
from dotshell.backends import Backend

from dotshell_sim.devices import (
    ANALYZER_SCHEMA, CAMERA_SCHEMA, LASER_SCHEMA, PROJECTOR_SCHEMA, TURNTABLE_SCHEMA, SimAnalyzer,
    SimCamera, SimLaser, SimProjector, SimTurntable, SimWorld, make_analyzer, make_camera,
    make_laser, make_projector, make_turntable, world_of)
from dotshell_sim.faults import FAULTY_CAMERA_SCHEMA, make_faulty_camera

__all__ = ["SimAnalyzer", "SimCamera", "SimLaser", "SimProjector", "SimTurntable", "SimWorld",
           "world_of"]


@hookimpl
def dotshell_cameras() -> list[Backend]:
    return [Backend("sim-camera", make_camera, CAMERA_SCHEMA,
                    "simulated camera: ray-cast scene, supersampling, defocus, shot/read noise, "
                    "ADC; knows the ground-truth calibration"),
            Backend("sim-camera-faulty", make_faulty_camera, FAULTY_CAMERA_SCHEMA,
                    "the simulated camera with one frame fault (late, reset, duplicate) to "
                    "prove frame-integrity checks")]


@hookimpl
def dotshell_projectors() -> list[Backend]:
    return [Backend("sim-projector", make_projector, PROJECTOR_SCHEMA,
                    "simulated projector: pose by position/look-at, distortion, defocus")]


@hookimpl
def dotshell_stages() -> list[Backend]:
    return [Backend("sim-turntable", make_turntable, TURNTABLE_SCHEMA,
                    "simulated turntable carrying the scene (cylinder, plate, background)")]


@hookimpl
def dotshell_analyzers() -> list[Backend]:
    return [Backend("sim-analyzer", make_analyzer, ANALYZER_SCHEMA,
                    "simulated polarization analyzer (stores its angle; no optics yet)")]


@hookimpl
def dotshell_light_sources() -> list[Backend]:
    return [Backend("sim-laser", make_laser, LASER_SCHEMA,
                    "simulated trans-illumination laser: diffusion FEM through the true sample, "
                    "aimable beam, flat-field diffuser, true exit radiance")]
