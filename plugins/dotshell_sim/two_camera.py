"""``python -m dotshell_sim.two_camera PROFILE OUT_DIR [--scale F] [--set KEY=VALUE ...]``:
the captures a lab's two-camera rig would hand to dotshell, made by the simulated rig of a
profile with a ``[camera2]`` (``profiles/sim-metal-cylinder-two-camera.toml``).

Two cameras sharing one projector capture outside dotshell (each camera's frames are saved by
the lab's own program); dotshell calibrates and reconstructs them from the files
(``calibrate --camera-pair``, ``calibrate --captures``, ``reconstruct --captures
--captures2``). This tool plays that lab. The projector shows OpenCV's GrayCodePattern
sequence (the shipped ``opencv-graycode`` layout, its projector size set to the profile's), and
``OUT_DIR`` receives:

=========================  ==================================================================
``layout.toml``            the layout of every sequence below
``cam1/``, ``cam2/``       each camera's sequence of the sample (stage at 0°)
``board1/``, ``board2/``   each camera's photo of the board (projector white) in every
                           ``[calibrate]`` pose, ``photo_NN.png``, paired in name order
``poses/poseN/``           camera 1's sequence of the board in the first five poses
``truth/``                 the simulator's truth: ``calibration.json`` (camera 1, projector,
                           turntable axis), ``camera-pair.json`` (both lenses, camera 2's pose)
``profile.toml``           the profile as rendered (``--scale`` and ``--set`` applied)
=========================  ==================================================================

Every pose is one state of the room seen by both cameras: each sim camera renders its own
copy of the rig (the projector and turntable moved into its frame, see ``position_mm`` of
``sim-camera``), and camera 2's copy of the stage is turned by the angle between the two
cameras about the axis, since a sim stage's angle 0 faces the camera that renders it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

#: Board poses of ``[calibrate]`` whose gray-code sequences camera 1 captures for the
#: camera–projector calibration (``calibrate --captures``).
PROJECTOR_POSES = 5


def layout_images(layout, pm) -> list[tuple[str, np.ndarray]]:
    """(file name, projector image) of each frame of a layout's sequence, in capture order:
    the layout's coding's own patterns (bit 1 lit) in the order
    :func:`~dotshell.run.capture_layouts.capture_order` reads them back."""
    from dotshell.errors import RunError
    from dotshell.run.capture_layouts import capture_order, layout_coding

    if not layout.bright_is_one:
        raise RunError(f"{layout.source}: bright_is_one = false is not rendered by this tool; "
                       "use a layout whose lit stripe means bit 1.")
    images = {p.name: p.image for p in layout_coding(layout, pm).patterns(layout.projector_size)}
    order = capture_order(layout, list(images))
    return [(layout.file_name(i), images[name]) for i, name in enumerate(order)]


def sim_rigs(raw: dict[str, Any], where: str) -> list[dict[str, Any]]:
    """Both cameras' connected sim rigs: camera 1 with the profile's projector and stage, and
    camera 2 (``[camera2]``) with its own copy of them."""
    from dotshell.errors import ProfileError
    from dotshell_sim.bench import build_rig

    for role in ("camera", "camera2", "projector", "stage"):
        backend = (raw.get(role) or {}).get("backend", "")
        if not backend.startswith("sim-"):
            raise ProfileError(f"{where}: [{role}] is {backend or 'missing'}; this simulator "
                               "tool needs a sim-camera as [camera] and [camera2], a "
                               "sim-projector and a sim-turntable.")
    rigs = []
    for camera in ("camera", "camera2"):
        rig = build_rig({**raw, "camera": raw[camera]})
        for device in rig.values():
            device.connect()
        rigs.append(rig)
    return rigs


def camera2_pose(rigs: list[dict[str, Any]]) -> tuple[np.ndarray, np.ndarray]:
    """(R, T) with ``X2 = R X1 + T`` (mm): camera 2's pose in camera 1's frame."""
    (R1, T1), (R2, T2) = (rig["camera"].pose() for rig in rigs)
    R = R2 @ R1.T
    return R, T2 - R @ T1


def stage_offsets_deg(rigs: list[dict[str, Any]]) -> tuple[float, float]:
    """Stage angle to add in each camera's copy of the rig so both show one room: 0 for camera
    1; for camera 2 the turn about the axis from camera 1's stage frame to its own."""
    R, _ = camera2_pose(rigs)
    b1, b2 = (rig["camera"].ground_truth_calibration().stage_basis() for rig in rigs)
    turn = b2 @ R @ b1.T
    return 0.0, float(np.degrees(np.arctan2(turn[1, 0], turn[0, 0])))


def render_sequence(rig: dict[str, Any], frames: list[tuple[str, np.ndarray]],
                    folder: Path) -> None:
    """Show each frame's image, capture, and write it losslessly as ``folder/<name>``."""
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    for name, image in frames:
        rig["projector"].show(image)
        cv2.imwrite(str(folder / name), rig["camera"].capture())


def place_board(rig: dict[str, Any], board: dict[str, Any], pose: list[float]) -> None:
    """The board on the stage at ``[roll, tilt, pan (deg), x, y, z (mm)]`` (sample frame)."""
    rig["stage"].place_target(board, {"rotation_deg": pose[:3], "centre_mm": pose[3:]})


def write_board_photos(rigs: list[dict[str, Any]], offsets: tuple[float, float], profile,
                       out: Path) -> int:
    """Each camera's photo of the board (projector white) in every ``[calibrate]`` pose,
    ``out/boardK/photo_NN.png``; returns the number of poses."""
    import cv2

    from dotshell.calibration.board import Board

    board = Board.from_settings(profile.calibrate.as_table()).sim_dict()
    w, h = rigs[0]["projector"].resolution
    for k, (rig, offset) in enumerate(zip(rigs, offsets)):
        rig["camera"].set_exposure(profile.calibrate.exposure_ms)
        rig["stage"].move_to(offset)
        rig["projector"].show(np.full((h, w), 255, np.uint8))
        (out / f"board{k + 1}").mkdir(exist_ok=True)
        for i, pose in enumerate(profile.calibrate.poses):
            place_board(rig, board, list(map(float, pose)))
            cv2.imwrite(str(out / f"board{k + 1}" / f"photo_{i:02d}.png"),
                        rig["camera"].capture())
    return len(profile.calibrate.poses)


def write_board_sequences(rig: dict[str, Any], frames: list[tuple[str, np.ndarray]], profile,
                          out: Path) -> int:
    """Camera 1's sequence of the board in the first :data:`PROJECTOR_POSES` poses,
    ``out/poses/poseN/``; returns how many."""
    from dotshell.calibration.board import Board

    board = Board.from_settings(profile.calibrate.as_table()).sim_dict()
    poses = profile.calibrate.poses[:PROJECTOR_POSES]
    rig["camera"].set_exposure(profile.calibrate.exposure_ms)
    rig["stage"].move_to(0.0)
    for i, pose in enumerate(poses):
        place_board(rig, board, list(map(float, pose)))
        render_sequence(rig, frames, out / "poses" / f"pose{i + 1}")
    rig["stage"].place_target(None, None)
    return len(poses)


def write_truth(rigs: list[dict[str, Any]], out: Path) -> None:
    """``out/truth/calibration.json`` (camera 1, projector, turntable axis) and
    ``out/truth/camera-pair.json`` (both lenses, camera 2's pose), in the formats of
    ``calibrate --captures`` and ``calibrate --camera-pair``."""
    from dotshell.calibration.camera_only import PAIR_FORMAT

    truth = [rig["camera"].ground_truth_calibration() for rig in rigs]
    (out / "truth").mkdir(exist_ok=True)
    truth[0].save(out / "truth" / "calibration.json")
    R, T = camera2_pose(rigs)
    (out / "truth" / "camera-pair.json").write_text(json.dumps({
        "format": PAIR_FORMAT, "camera1": truth[0].camera.to_dict(),
        "camera2": truth[1].camera.to_dict(), "R": R.tolist(), "T": T.tolist(), "rms_px": 0.0},
        indent=1))


def write_captures(raw: dict[str, Any], pm, out: Path, where: str) -> dict[str, int]:
    """Everything :mod:`this tool <dotshell_sim.two_camera>` writes; returns the counts."""
    import tomli_w

    from dotshell.profile.loader import validate_profile
    from dotshell.run.capture_layouts import load_layout

    profile = validate_profile(raw, pm, where)
    rigs = sim_rigs(raw, where)
    try:
        size = rigs[0]["projector"].resolution
        layout = dataclasses.replace(load_layout("opencv-graycode"), projector_size=size)
        out.mkdir(parents=True, exist_ok=True)
        (out / "layout.toml").write_text(tomli_w.dumps(layout.as_dict()))
        (out / "profile.toml").write_text(tomli_w.dumps(profile.raw()))
        frames = layout_images(layout, pm)
        offsets = stage_offsets_deg(rigs)
        for k, (rig, offset) in enumerate(zip(rigs, offsets)):
            rig["camera"].set_exposure(profile.scan.exposure_ms)
            rig["stage"].move_to(offset)
            render_sequence(rig, frames, out / f"cam{k + 1}")
        photos = write_board_photos(rigs, offsets, profile, out)
        sequences = write_board_sequences(rigs[0], frames, profile, out)
        write_truth(rigs, out)
    finally:
        for rig in rigs:
            for device in rig.values():
                device.close()
    return {"frames": len(frames), "photos": photos, "projector_poses": sequences}


def next_commands(out: Path, board: str) -> list[str]:
    """The documented commands that calibrate and reconstruct what was written."""
    pair = "runs/<time>_calibrate-camera-pair/camera-pair.json"
    calib = "runs/<time>_calibrate-opencv-graycode/calibration.json"
    layout = f"--layout {out}/layout.toml"
    both = f"--captures {out}/cam1 --captures2 {out}/cam2 --camera-pair {pair} {layout}"
    return [f"dotshell calibrate --camera-pair {out}/board1 {out}/board2 {board} --out runs",
            f"dotshell reconstruct {both} --out runs",
            "  with the projector calibrated too (fused):",
            f"dotshell calibrate --captures {out}/poses/pose* {layout} {board} --out runs",
            f"dotshell reconstruct {both} --calibration {calib} --out runs"]


def main(argv: Sequence[str] | None = None) -> int:
    from dotshell.errors import DotshellError
    from dotshell.plugins import get_plugin_manager
    from dotshell.profile.loader import load_profile
    from dotshell_sim.bench import scale_profile

    ap = argparse.ArgumentParser(prog="python -m dotshell_sim.two_camera",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("profile", help="profile with [camera2], e.g. sim-metal-cylinder-two-camera")
    ap.add_argument("out", help="directory to write the captures into")
    ap.add_argument("--scale", type=float, default=1.0,
                    help="resolution factor of both cameras and the projector (0.25: 320x256)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a profile key (TOML value), e.g. calibrate.square_mm=3")
    args = ap.parse_args(argv)
    pm = get_plugin_manager()
    try:
        if not args.scale > 0:
            raise DotshellError(f"--scale {args.scale:g}: give a positive factor, e.g. 0.25.")
        profile = load_profile(args.profile, pm, args.set)
        raw = profile.raw()
        if args.scale != 1:
            raw = scale_profile(raw, args.scale)
        counts = write_captures(raw, pm, Path(args.out), profile.source)
    except DotshellError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    c = profile.calibrate
    print(f"{args.out}: {counts['frames']} frames per camera (cam1/, cam2/), "
          f"{counts['photos']} board photos per camera (board1/, board2/), "
          f"{counts['projector_poses']} board sequences of camera 1 (poses/), layout.toml, "
          "truth/")
    print("next:")
    for line in next_commands(Path(args.out),
                              f"--board {c.columns}x{c.rows} --square {c.square_mm:g}"):
        print(f"  {line}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
