"""Foreign capture sequences rendered by the simulated rig, with their ground truth (tests only).

A sequence of projector images (e.g. OpenCV's, :mod:`opencv_graycode`) is shown by the sim
projector and captured by the sim camera into a directory under the names another program
would give the files; the renderer's ray trace gives the true projector coordinates of every
camera pixel centre.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from dotshell_sim.bench import build_rig

CYLINDER, PLATE = 0, 1  # material ids of the reference scene


def connected_rig(raw_profile: dict) -> dict:
    """The profile's sim devices, connected, camera exposure set from ``[scan]``."""
    rig = build_rig(raw_profile)
    for device in rig.values():
        device.connect()
    rig["camera"].set_exposure(float(raw_profile["scan"]["exposure_ms"]))
    return rig


def render_sequence(rig: dict, images: list[np.ndarray], directory: Path,
                    name_of: Callable[[int], str], angle_deg: float = 0.0) -> Path:
    """Show each image, capture a frame and write it losslessly as ``directory/name_of(i)``."""
    directory.mkdir(parents=True, exist_ok=True)
    rig["stage"].move_to(angle_deg)
    for i, img in enumerate(images):
        rig["projector"].show(img)
        cv2.imwrite(str(directory / name_of(i)), rig["camera"].capture())
    return directory


def true_projector_coordinates(rig: dict, angle_deg: float = 0.0
                               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(column, row, lit) per camera pixel: the projector pixel coordinates of the surface hit
    by each pixel centre's ray, and the pixels whose whole footprint lies on the cylinder or
    the plate and is lit by the projector (the pixels a decoder must get right)."""
    cam = rig["camera"]
    renderer = cam.world.renderer()
    w, h = cam.resolution
    ys, xs = np.mgrid[0:h, 0:w]
    trace = renderer.trace(np.column_stack([xs.ravel(), ys.ravel()]).astype(np.float64),
                           angle_deg)
    view = renderer.view(angle_deg)
    on_surface = (view.material_fraction(CYLINDER) == 1) | (view.material_fraction(PLATE) == 1)
    lit = on_surface & (view.lit_fraction() == 1)
    return (trace.projector[:, 0].reshape(h, w), trace.projector[:, 1].reshape(h, w), lit)


def render_board_poses(rig: dict, board: dict, poses: list[list[float]],
                       images: list[np.ndarray], parent: Path, name_of: Callable[[int], str],
                       exposure_ms: float = 10.0) -> list[Path]:
    """One folder per board pose (``[roll, tilt, pan (deg), x, y, z (mm)]``, sample frame,
    stage at 0°), each holding the whole sequence ``images`` as captured frames."""
    rig["camera"].set_exposure(exposure_ms)
    out = []
    for k, pose in enumerate(poses):
        rig["stage"].place_target(board, {"rotation_deg": list(pose[:3]),
                                          "centre_mm": list(pose[3:])})
        out.append(render_sequence(rig, images, parent / f"pose{k + 1}", name_of))
    return out


def render_turntable(rig: dict, board: dict, pose: list[float], angles_deg: list[float],
                     directory: Path, exposure_ms: float = 10.0) -> Path:
    """The board standing on the stage at ``pose``, one white frame per stage angle
    (``angle_000.png``, ...)."""
    w, h = rig["projector"].resolution
    rig["camera"].set_exposure(exposure_ms)
    rig["stage"].place_target(board, {"rotation_deg": list(pose[:3]), "centre_mm": list(pose[3:])})
    directory.mkdir(parents=True, exist_ok=True)
    rig["projector"].show(np.full((h, w), 255, np.uint8))
    for k, a in enumerate(angles_deg):
        rig["stage"].move_to(a)
        cv2.imwrite(str(directory / f"angle_{k:03d}.png"), rig["camera"].capture())
    return directory
