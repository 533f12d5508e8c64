"""Calibration from pose folders captured anywhere (another program, another lab): each folder
holds one pose's whole sequence as a layout file describes it (``docs/layouts.md``), e.g. the
``pattern_cam1_im*.png`` files OpenCV's capture sample writes. :func:`calibrate_captures` writes
a calibration run whose ``capture.json`` names the layout and the frames where they are, and
solves it with :func:`dotshell.calibration.procedure.solve`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dotshell.calibration.board import Board
from dotshell.calibration.procedure import CAPTURE_FORMAT, CalibrationResult, read_image, solve
from dotshell.errors import CalibrationError
from dotshell.events import EventBus
from dotshell.run.capture_layouts import (capture_order, coding_frame_names, layout_coding, load_layout,
                                  sequence_files)
from dotshell.run.store import RunStore


@dataclass(frozen=True)
class TurntableFrames:
    """White frames of the board standing on the stage at known angles (for the axis).

    Attributes:
        directory: holds one image per angle; sorted by name (numbers in names compare as
            numbers) they are taken in the order of ``angles_deg``.
        angles_deg: stage angle of each image (degrees).
        board_height_mm: height of the board centre above the stage plate (mm).
    """

    directory: Path
    angles_deg: tuple[float, ...]
    board_height_mm: float


IMAGE_SUFFIXES = (".png", ".bmp", ".tif", ".tiff", ".jpg", ".jpeg", ".pgm")


def _natural_key(name: str) -> list:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def turntable_poses(t: TurntableFrames) -> list[dict[str, Any]]:
    """capture.json poses of the turntable frames (checks the count against the angles)."""
    d = Path(t.directory)
    if not d.is_dir():
        raise CalibrationError(f"turntable frames directory {d} does not exist.")
    images = sorted((p for p in d.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES),
                    key=lambda p: _natural_key(p.name))
    if len(images) != len(t.angles_deg):
        raise CalibrationError(
            f"{d}: {len(images)} images ({', '.join(p.name for p in images[:6])}) but "
            f"{len(t.angles_deg)} stage angles; give one angle per image, in name order.")
    return [{"name": f"turntable_{k:02d}", "kind": "turntable", "angle_deg": float(a),
             "centre_mm": [0.0, 0.0, float(t.board_height_mm)], "frames": [str(p.resolve())]}
            for k, (p, a) in enumerate(zip(images, t.angles_deg))]


def calibrate_captures(pose_dirs: list[Path | str], layout_file: Path | str, board: Board, pm,
                       settings: dict[str, Any], out_dir: Path | str = "runs",
                       turntable: TurntableFrames | None = None,
                       bus: EventBus | None = None) -> CalibrationResult:
    """Calibrate from pose folders captured anywhere: each folder holds one pose's whole
    sequence as the layout describes it (e.g. OpenCV's ``pattern_cam1_im*.png``). Writes a
    calibration run (``capture.json`` naming the layout and the frames where they are) under
    ``out_dir`` and solves it; the turntable axis only when ``turntable`` frames are given."""
    if not pose_dirs:
        raise CalibrationError("calibrate --captures needs at least one pose folder.")
    layout = load_layout(layout_file)
    if "rows" not in layout.order:
        raise CalibrationError(
            f"layout {layout.name!r} ({layout.source}) has no rows: calibrating the projector "
            "needs its columns and rows decoded. Capture the poses with a sequence that has "
            "row patterns (order with 'rows').")
    coding = layout_coding(layout, pm, axes="both")
    order = capture_order(layout, coding_frame_names(coding, layout.projector_size))
    poses: list[dict[str, Any]] = []
    for k, d in enumerate(pose_dirs):
        files = sequence_files(Path(d), layout, order)
        poses.append({"name": f"pose_{k:02d}", "kind": "free", "angle_deg": 0.0,
                      "folder": str(Path(d).resolve()),
                      "frames": [str(f.resolve()) for f in files]})
    first = read_image(Path(poses[0]["folder"]), poses[0]["frames"][order.index("white")])
    if turntable is not None:
        poses += turntable_poses(turntable)
    store = RunStore.create(Path(out_dir), f"calibrate-{layout.name}")
    store.write_json("capture.json", {
        "format": CAPTURE_FORMAT, "board": board.as_dict(),
        "coding": {"backend": layout.coding, "settings": layout.coding_settings()},
        "layout": layout.as_dict(),
        "camera_size": [int(first.shape[1]), int(first.shape[0])],
        "projector_size": list(layout.projector_size), "poses": poses})
    store.close()
    return solve(store.root, settings, pm, bus)
