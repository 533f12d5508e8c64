"""The simulator's backends, each built on first use (``python_name`` targets of this package's
``dotshell.toml``): importing this module imports no part of the simulator."""

from __future__ import annotations

from dotshell.backends import Backend


def sim_camera() -> Backend:
    from dotshell_sim.devices import CAMERA_SCHEMA, make_camera

    return Backend("sim-camera", make_camera, CAMERA_SCHEMA)


def sim_camera_faulty() -> Backend:
    from dotshell_sim.faults import FAULTY_CAMERA_SCHEMA, make_faulty_camera

    return Backend("sim-camera-faulty", make_faulty_camera, FAULTY_CAMERA_SCHEMA)


def sim_projector() -> Backend:
    from dotshell_sim.devices import PROJECTOR_SCHEMA, make_projector

    return Backend("sim-projector", make_projector, PROJECTOR_SCHEMA)


def sim_turntable() -> Backend:
    from dotshell_sim.devices import TURNTABLE_SCHEMA, make_turntable

    return Backend("sim-turntable", make_turntable, TURNTABLE_SCHEMA)


def sim_analyzer() -> Backend:
    from dotshell_sim.devices import ANALYZER_SCHEMA, make_analyzer

    return Backend("sim-analyzer", make_analyzer, ANALYZER_SCHEMA)


def sim_laser() -> Backend:
    from dotshell_sim.devices import LASER_SCHEMA, make_laser
    from dotshell_sim.transillum import compile_kernels

    return Backend("sim-laser", make_laser, LASER_SCHEMA, compile_kernels=compile_kernels)
