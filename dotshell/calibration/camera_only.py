"""Camera-only calibration from plain photos of the board (no projector, no pattern sequence).

Each image is one pose of the board; the board's corners give the camera's intrinsics and
distortion with the lens model chosen as for a rig (:mod:`dotshell.calibration.models`). The
result is written to a run directory::

    <out>/<time>_calibrate-camera/
        camera.json              format dotshell-camera-calibration/1 (docs/calibration.md)
        calibration-report.json  model choice, coefficients with one-sigma, coverage, poses
        report/residuals_<pose>.png

Lengths in mm, image quantities in pixels.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from dotshell.calibration.board import Board, detect
from dotshell.calibration.models import (
    COEFFICIENTS,
    MODEL_TERMS,
    choose_model,
    solve_candidate,
)
from dotshell.calibration.solve import (
    LensSolve,
    OutlierRule,
    PoseData,
    calibrate_lens,
    initial_matrix,
)
from dotshell.errors import CalibrationError
from dotshell.geometry.lens import Lens
from dotshell.run.capture_layouts import read_gray

CAMERA_FORMAT = "dotshell-camera-calibration/1"


@dataclass
class CameraResult:
    """The solved camera, its report (as written) and the run directory."""

    lens: Lens
    report: dict[str, Any]
    run_dir: Path


def board_images(paths: list[Path | str]) -> list[Path]:
    """Image files given directly or as folders (sorted by name, numbers compared as numbers)."""
    from dotshell.calibration.captures import IMAGE_SUFFIXES, _natural_key

    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            out += sorted((q for q in p.iterdir() if q.suffix.lower() in IMAGE_SUFFIXES),
                          key=lambda q: _natural_key(q.name))
        elif p.is_file():
            out.append(p)
        else:
            raise CalibrationError(f"{p}: no such image or folder of board photos.")
    if not out:
        raise CalibrationError(f"no board photos ({', '.join(IMAGE_SUFFIXES)}) in "
                               f"{', '.join(map(str, paths))}.")
    return out


def _detect_all(images: list[Path], board: Board, max_blur_px: float
                ) -> tuple[list[PoseData], dict[str, str], dict[str, Any], tuple[int, int]]:
    """Poses from the photos where the board is found sharp; the others left out (named)."""
    from dotshell.calibration.procedure import _refuse_other_count

    objp = board.object_points()
    poses: list[PoseData] = []
    left_out: dict[str, str] = {}
    report: dict[str, Any] = {}
    size: tuple[int, int] | None = None
    for k, path in enumerate(images):
        img, _kind = read_gray(path)
        here = (img.shape[1], img.shape[0])
        size = size or here
        if here != size:
            raise CalibrationError(f"{path}: {here[0]}x{here[1]} px, but {images[0].name} is "
                                   f"{size[0]}x{size[1]}: all photos must come from this camera "
                                   "at one resolution.")
        name = f"pose_{k:02d}"
        report[name] = {"image": str(path)}
        det = detect(img, board)
        if det is None:
            if k == 0:
                _refuse_other_count(img, board, str(path))
            left_out[name] = f"target not found in {path}"
            continue
        report[name].update(corners=int(len(det.ids)), sharpness_px=det.sharpness_px)
        if det.sharpness_px > max_blur_px:
            left_out[name] = f"blurred: edges {det.sharpness_px:.1f} px wide in {path}"
            continue
        poses.append(PoseData(name, objp[det.ids], det.pixels))
    if size is None:  # board_images() refuses an empty list first
        raise CalibrationError("no board photos given.")
    return poses, left_out, report, size


def calibrate_camera(paths: list[Path | str], board: Board, settings: dict[str, Any],
                     out_dir: Path | str = "runs") -> CameraResult:
    """Solve a camera from plain board photos (``settings``: ``[calibrate]``) and write the run
    directory described in the module docstring."""
    from dotshell.calibration.report import (
        coverage_pct,
        lens_warnings,
        write_residual_pictures,
    )
    from dotshell.run.store import RunStore

    images = board_images(paths)
    poses, left_out, poses_report, size = _detect_all(images, board, settings["max_blur_px"])
    if not poses:
        raise CalibrationError(
            f"the {board.kind} ({board.columns}x{board.rows} squares) was not found in any "
            f"photo: {', '.join(p.name for p in images[:6])}. Check the target and its counts "
            "(--board COLSxROWS: squares, not inner corners), exposure and focus.")
    rule = OutlierRule(settings["min_poses"], settings["outlier_factor"], settings["max_rms_px"])
    distortion = settings["distortion"]
    first = calibrate_lens("camera", poses, size, "full" if distortion == "auto" else distortion,
                           rule, left_out)
    kept = [p for p in poses if p.name in first.per_pose_rms_px]
    choice = choose_model("camera", kept, size) if distortion == "auto" else None
    model = choice.chosen if choice else distortion
    solved = calibrate_lens("camera", poses, size, model, rule, first.left_out)
    kept = [p for p in poses if p.name in solved.per_pose_rms_px]
    cand = solve_candidate(kept, size, model, initial_matrix(size, kept))
    lens = solved.lens
    residuals = {}
    for p in kept:
        px, _ = cv2.projectPoints(p.object_points, solved.rvecs[p.name], solved.tvecs[p.name],
                                  lens.K, lens.dist)
        residuals[p.name] = {"camera": (p.image_points, px.reshape(-1, 2) - p.image_points)}
        poses_report[p.name]["camera_rms_px"] = solved.per_pose_rms_px[p.name]
    coverage = coverage_pct([p.image_points for p in kept], size)
    values = dict(zip(("fx", "fy", "cx", "cy") + COEFFICIENTS,
                      (lens.K[0, 0], lens.K[1, 1], lens.K[0, 2], lens.K[1, 2], *lens.dist)))
    solved_terms = ("fx", "fy", "cx", "cy") + MODEL_TERMS[model]
    coefficients = {k: {"value": float(v), "sigma": cand.sigma[k] if k in solved_terms else None}
                    for k, v in values.items()}
    sigma = {k: cand.sigma[k] for k in solved_terms}
    report = {
        "format": CAMERA_FORMAT, "camera": lens.to_dict(), "rms_px": solved.rms_px,
        "model": {"model": model, "terms": list(MODEL_TERMS[model]),
                  **(choice.as_dict() if choice else {"reason": "given by [calibrate] distortion"})},
        "coefficients": coefficients, "coverage_pct": coverage,
        "warnings": lens_warnings("camera", lens, sigma, model, coverage,
                                  settings.get("warn_sigma_pct", 0.25)),
        "left_out": solved.left_out, "poses": poses_report,
    }
    store = RunStore.create(Path(out_dir), "calibrate-camera")
    (store.root / "report").mkdir(exist_ok=True)
    pictures = write_residual_pictures(store.root / "report", residuals, {"camera": size})
    report["residual_pictures"] = {n: f"report/{f}" for n, f in pictures.items()}
    store.write_json("camera.json", {k: report[k] for k in ("format", "camera", "rms_px")}
                     | {"model": model, "sigma": sigma})
    store.write_json("calibration-report.json", report)
    store.close()
    return CameraResult(lens, report, store.root)


@dataclass
class PairSolve:
    """Two cameras solved together: both lenses, camera 2's pose in camera 1's frame
    ``X2 = R X1 + T`` (mm), the joint RMS (px) and the poses used."""

    camera1: Lens
    camera2: Lens
    R: np.ndarray
    T: np.ndarray
    rms_px: float
    poses: list[str]


def calibrate_pair(poses1: list[PoseData], poses2: list[PoseData], solve1: LensSolve,
                   solve2: LensSolve, models: tuple[str, str]) -> PairSolve:
    """Two cameras from board photos taken by both at once (poses matched by name, corners by
    board point): their pose from OpenCV's stereo solve with each lens as solved alone, then
    one bundle adjustment of both lenses (each with its model), the pose and every board pose
    (:func:`dotshell.calibration.bundle.bundle_adjust`, camera 2 in the projector's place)."""
    from dotshell.calibration.bundle import bundle_adjust

    lens1, lens2 = solve1.lens, solve2.lens
    by2 = {p.name: p for p in poses2}
    obj, img1, img2, names = [], [], [], []
    for p in poses1:
        q = by2.get(p.name)
        if q is None or p.name not in solve1.rvecs:
            continue
        key = {tuple(np.round(o, 6)): i for i, o in enumerate(q.object_points)}
        pairs = [(i, key[tuple(np.round(o, 6))]) for i, o in enumerate(p.object_points)
                 if tuple(np.round(o, 6)) in key]
        if len(pairs) < 6:
            continue
        i1, i2 = np.array(pairs).T
        obj.append(p.object_points[i1].astype(np.float32).reshape(-1, 1, 3))
        img1.append(p.image_points[i1].astype(np.float32).reshape(-1, 1, 2))
        img2.append(q.image_points[i2].astype(np.float32).reshape(-1, 1, 2))
        names.append(p.name)
    if len(names) < 3:
        raise CalibrationError(f"camera pair: {len(names)} board photos seen by both cameras, "
                               "at least 3 are needed (the same board pose photographed by "
                               "each camera, named alike).")
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    out = cv2.stereoCalibrate(obj, img1, img2, lens1.K, lens1.dist, lens2.K, lens2.dist,
                              lens1.size, flags=cv2.CALIB_FIX_INTRINSIC, criteria=crit)
    kept2 = [by2[n] for n in names]
    joint = bundle_adjust([p for p in poses1 if p.name in names], kept2, lens1, lens2,
                          np.asarray(out[5]), np.asarray(out[6]).ravel(), solve1.rvecs,
                          solve1.tvecs, models)
    return PairSolve(joint.camera, joint.projector, joint.R, joint.T, joint.rms_px, names)


PAIR_FORMAT = "dotshell-camera-pair/1"


def calibrate_camera_pair(dir1: Path | str, dir2: Path | str, board: Board,
                          settings: dict[str, Any], out_dir: Path | str = "runs"
                          ) -> tuple[PairSolve, Path]:
    """Two cameras from board photos both took: ``dir1`` and ``dir2`` hold one photo per board
    pose each, paired in name order. Each lens is solved alone (model by held-out poses), then
    both with their pose (:func:`calibrate_pair`); writes ``camera-pair.json`` (format
    ``dotshell-camera-pair/1``) into a new run directory and returns (solve, directory)."""
    from dotshell.run.store import RunStore

    images = [board_images([d]) for d in (dir1, dir2)]
    if len(images[0]) != len(images[1]):
        raise CalibrationError(f"camera pair: {dir1} holds {len(images[0])} photos but {dir2} "
                               f"{len(images[1])}; each board pose needs one photo from each "
                               "camera (paired in name order).")
    rule = OutlierRule(settings["min_poses"], settings["outlier_factor"], settings["max_rms_px"])
    found, solves, models = [], [], []
    for imgs in images:
        poses, left_out, _, size = _detect_all(imgs, board, settings["max_blur_px"])
        if not poses:
            raise CalibrationError(f"camera pair: the board was not found in any photo of "
                                   f"{imgs[0].parent} (--board COLSxROWS counts squares).")
        model = (choose_model("camera", poses, size).chosen if settings["distortion"] == "auto"
                 else settings["distortion"])
        found.append(poses)
        models.append(model)
        solves.append(calibrate_lens("camera", poses, size, model, rule, left_out))
    pair = calibrate_pair(found[0], found[1], solves[0], solves[1], (models[0], models[1]))
    if not pair.rms_px <= settings["max_rms_px"]:
        raise CalibrationError(
            f"camera pair refused: joint RMS {pair.rms_px:.3g} px > max_rms_px "
            f"{settings['max_rms_px']:g} px over {len(pair.poses)} poses; nothing written. "
            "Check that --board COLSxROWS counts the squares (a board with an even number of "
            "inner corners both ways reads the same turned by 180°: use one with an odd count "
            "one way) and that both folders hold photos of the same poses in the same name "
            "order.")
    store = RunStore.create(Path(out_dir), "calibrate-camera-pair")
    store.write_json("camera-pair.json", {
        "format": PAIR_FORMAT, "camera1": pair.camera1.to_dict(), "camera2": pair.camera2.to_dict(),
        "R": pair.R.tolist(), "T": pair.T.tolist(), "rms_px": pair.rms_px, "models": models,
        "poses": pair.poses, "photos": [str(Path(d).resolve()) for d in (dir1, dir2)]})
    store.close()
    return pair, store.root


def load_camera_pair(path: Path | str) -> PairSolve:
    """A ``camera-pair.json`` written by :func:`calibrate_camera_pair`."""
    import json

    try:
        d = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise CalibrationError(f"{path}: not a readable camera-pair file ({exc}).") from None
    if d.get("format") != PAIR_FORMAT:
        raise CalibrationError(f"{path}: format is {d.get('format')!r}, expected {PAIR_FORMAT!r} "
                               "(written by dotshell calibrate --camera-pair).")
    return PairSolve(Lens.from_dict(d["camera1"]), Lens.from_dict(d["camera2"]),
                     np.array(d["R"], float), np.array(d["T"], float), float(d["rms_px"]),
                     list(d.get("poses", [])))
