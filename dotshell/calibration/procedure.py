"""The calibration procedure: capture the target at the profile's poses into a calibration run
directory — or gather pose folders captured anywhere (:func:`calibrate_captures`) — then solve
camera, projector, camera–projector pose and (when turntable frames are given) the turntable axis
from the frames on disk, so a capture can be solved again.

Run directory::

    <out>/<time>_calibrate-<profile>/
        profile.toml  capture.json  frames/pose_00/000_white.png ...  frames/turntable_00/...
        calibration.json  calibration.yml  calibration-report.json  [ground_truth.json]
        report/residuals_<pose>.png  residual vectors per pose (camera | projector)
        [calibration-refused.json]   a solve out of bounds: its figures (nothing else written)

``capture.json`` (format ``dotshell-calibration-capture/1``, documented in
docs/calibration.md) lists the board, the ONE coding that decodes the frames (backend and
settings), optionally the layout the frames were captured in, the camera and projector sizes
and, per pose, its name, kind (``free`` or ``turntable``), stage angle and frame files.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Protocol, runtime_checkable

import cv2
import numpy as np

from dotshell.calibration.board import Board, detect, flipped
from dotshell.calibration.bundle import bundle_adjust
from dotshell.calibration.models import choose_model
from dotshell.calibration.solve import (OutlierRule, PoseData, calibrate_lens, calibrate_stereo,
                                        projector_corners, turntable_axis)
from dotshell.errors import CalibrationError
from dotshell.events import EventBus, StepProgress, StepStarted
from dotshell.run.layout import RunLayout
from dotshell.geometry.calibration import (PLACEHOLDER_AXIS_DIRECTION, PLACEHOLDER_AXIS_POINT,
                                           RigCalibration)

CAPTURE_FORMAT = "dotshell-calibration-capture/1"
#: The issue's acceptance limits for a calibration against the simulator's ground truth.
ACCEPTANCE = {"focal_pct": 0.2, "principal_px": 1.0, "baseline_pct": 0.2,
              "axis_direction_deg": 0.1, "axis_point_mm": 0.1}


@runtime_checkable
class TargetPlacement(Protocol):
    """A stage that can put the calibration board at a pose by itself (the simulator's)."""

    def place_target(self, board: dict | None, pose: dict | None) -> None:
        ...


@dataclass(frozen=True)
class PoseSpec:
    name: str
    kind: str            # "free" or "turntable"
    angle_deg: float
    rotation_deg: tuple[float, float, float]
    centre_mm: tuple[float, float, float]

    def describe(self) -> str:
        r, c = self.rotation_deg, self.centre_mm
        where = (f"roll {r[0]:g}°, tilt {r[1]:g}°, pan {r[2]:g}°, centre ({c[0]:g}, {c[1]:g}, "
                 f"{c[2]:g}) mm on the stage")
        return f"{self.name}: stage at {self.angle_deg:g}°, board {where}"


def pose_specs(settings: Mapping[str, Any]) -> list[PoseSpec]:
    """The poses of a profile's ``[calibrate]`` section, free poses first."""
    out = []
    for k, row in enumerate(settings["poses"]):
        if len(row) != 6:
            raise CalibrationError(f"[calibrate] poses row {k} = {row} needs 6 numbers: roll, "
                                   "tilt, pan (deg), centre x, y, z (mm).")
        out.append(PoseSpec(f"pose_{k:02d}", "free", 0.0, tuple(row[:3]), tuple(row[3:])))
    tp = settings["turntable_pose"]
    for k, a in enumerate(settings["turntable_angles_deg"]):
        out.append(PoseSpec(f"turntable_{k:02d}", "turntable", float(a), tuple(tp[:3]),
                            tuple(tp[3:])))
    return out


def _coding_spec(profile) -> tuple[str, dict[str, Any]]:
    c = profile.role("coding")
    settings = dict(c["settings"])
    if "axes" in settings:
        settings["axes"] = "both"  # projector calibration needs columns and rows
    return c["backend"], settings


def _write_png(path: Path, image: np.ndarray) -> None:
    from dotshell.run.store import atomic_write_bytes

    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise CalibrationError(f"cannot encode frame {path}")
    atomic_write_bytes(path, buf.tobytes())


def capture(profile, pm, out_dir: Path | str = "runs", bus: EventBus | None = None,
            ask: Callable[[str], None] | None = None) -> Path:
    """Capture the target at every pose of ``[calibrate]``; returns the run directory.

    A stage that satisfies :class:`TargetPlacement` places the board itself; otherwise
    ``ask(message)`` is called before each pose (the CLI waits for Enter).
    """
    from dotshell.devices import ExposureControl, GroundTruth
    from dotshell.rig.assembly import Rig
    from dotshell.run.store import RunStore

    bus = bus or EventBus()
    settings = profile.calibrate
    specs = pose_specs(settings)
    if not specs:
        raise CalibrationError(f"{profile.source}: [calibrate] lists no poses; add poses = "
                               "[[roll, tilt, pan, x, y, z], ...] and turntable_angles_deg.")
    board = Board.from_settings(settings)
    backend, coding_settings = _coding_spec(profile)
    coding = pm.create("coding", backend, coding_settings, None, profile.source)
    store = RunStore.create(Path(out_dir), f"calibrate-{profile.name}")
    store.write_profile(profile.raw())
    poses_out = []
    with Rig(profile, pm) as rig:
        patterns = coding.patterns(rig.projector.resolution)
        white = next((p for p in patterns if p.name == "white"), None)
        if white is None:
            raise CalibrationError(f"coding {backend!r} has no 'white' frame; calibration needs "
                                   "a coding whose sequence starts with white and black.")
        if isinstance(rig.camera, ExposureControl):
            rig.camera.set_exposure(settings.exposure_ms)
        placer = rig.stage if isinstance(rig.stage, TargetPlacement) else None
        total = sum(len(patterns) if s.kind == "free" else 1 for s in specs)
        bus.emit(StepStarted(step="calibration capture", total=total))
        done = 0
        for spec in specs:
            if placer is not None:
                placer.place_target(board.sim_dict(), {"rotation_deg": list(spec.rotation_deg),
                                                       "centre_mm": list(spec.centre_mm)})
            elif ask is not None:
                ask(f"Place the {board.kind} ({board.columns}x{board.rows} squares of "
                    f"{board.square_mm:g} mm) — {spec.describe()}")
            rig.stage.move_to(spec.angle_deg)
            shown = patterns if spec.kind == "free" else [white]
            files = []
            for i, pat in enumerate(shown):
                rig.projector.show(pat.image)
                frame = rig.camera.capture()
                rel = f"{RunLayout.FRAMES}/{spec.name}/{RunLayout.png_frame(i, pat.name)}"
                _write_png(store.path(rel), frame)
                files.append(rel)
                done += 1
                bus.emit(StepProgress(step="calibration capture", done=done, total=total))
            poses_out.append({"name": spec.name, "kind": spec.kind, "angle_deg": spec.angle_deg,
                              "rotation_deg": list(spec.rotation_deg),
                              "centre_mm": list(spec.centre_mm), "frames": files})
        if placer is not None:
            placer.place_target(None, None)
        truth = next((d.ground_truth_calibration() for d in rig.devices.values()
                      if isinstance(d, GroundTruth)), None)
        cam_size, proj_size = list(rig.camera.resolution), list(rig.projector.resolution)
    if truth is not None:
        truth.save(store.path("ground_truth.json"))
    store.write_json("capture.json", {
        "format": CAPTURE_FORMAT, "profile": profile.name, "board": board.as_dict(),
        "coding": {"backend": backend, "settings": coding_settings},
        "camera_size": cam_size, "projector_size": proj_size, "poses": poses_out})
    store.close()
    return store.root


# ---- solving from disk ------------------------------------------------------------------------

def read_image(run: Path, rel: str) -> np.ndarray:
    """A calibration frame, ``rel`` relative to ``run`` (or absolute), as written."""
    img = cv2.imread(str(run / rel), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise CalibrationError(f"{run / rel}: missing or not an image; the calibration capture "
                               "is incomplete.")
    return img


def _check_sizes(run: Path, pose: dict, frames: list[np.ndarray], size: tuple[int, int]) -> None:
    odd = [f"{rel} ({f.shape[1]}x{f.shape[0]})" for rel, f in zip(pose["frames"], frames)
           if (f.shape[1], f.shape[0]) != tuple(size)]
    if odd:
        raise CalibrationError(f"{run}: images of another size than the camera's "
                               f"{size[0]}x{size[1]} px: {', '.join(odd[:5])}. All calibration "
                               "images must come from this camera at one resolution.")


def _corner_spacing(px: np.ndarray) -> float:
    from scipy.spatial import cKDTree

    d, _ = cKDTree(px).query(px, k=2)
    return float(np.median(d[:, 1]))


@dataclass
class CalibrationResult:
    calibration: RigCalibration
    report: dict[str, Any]
    run_dir: Path


def read_capture(run: Path) -> dict[str, Any]:
    """A calibration run's ``capture.json``, checked for the keys the solve needs."""
    path = run / "capture.json"
    try:
        cap = json.loads(path.read_text())
    except FileNotFoundError:
        raise CalibrationError(f"{run}: no capture.json; give a directory written by `dotshell "
                               "calibrate` (the format is in docs/calibration.md).") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"{path}: not valid JSON ({exc}).") from None
    if cap.get("format") != CAPTURE_FORMAT:
        raise CalibrationError(f"{path}: format is {cap.get('format')!r}, expected "
                               f"{CAPTURE_FORMAT!r} (docs/calibration.md).")
    missing = [k for k in ("board", "coding", "camera_size", "projector_size", "poses")
               if k not in cap]
    if missing:
        raise CalibrationError(f"{path}: missing {', '.join(missing)} (docs/calibration.md "
                               "lists every key).")
    return cap


class PoseFrames:
    """Reads a pose's frames in the order of capture.json's coding: as listed when capture.json
    has no ``layout``, else reordered and their polarity undone as the layout says."""

    def __init__(self, run: Path, cap: dict[str, Any], pm) -> None:
        from dotshell.run.capture_layouts import capture_order, coding_frame_names, layout_from_dict

        where = str(run / "capture.json")
        self.run = run
        self.backend = cap["coding"]["backend"]
        self.settings = dict(cap["coding"]["settings"])
        self.coding = pm.create("coding", self.backend, self.settings, None, where)
        self.names = coding_frame_names(self.coding, tuple(cap["projector_size"]))
        self.layout = (layout_from_dict(cap["layout"], f"{where} [layout]")
                       if cap.get("layout") else None)
        self.order = capture_order(self.layout, self.names) if self.layout else self.names
        self.camera_size = tuple(cap["camera_size"])

    def white(self, pose: dict) -> str:
        """The file of the pose's white frame (where the target is detected)."""
        files = pose["frames"]
        return files[self.order.index("white")] if len(files) == len(self.order) else files[0]

    def __call__(self, pose: dict) -> list[np.ndarray]:
        from dotshell.run.capture_layouts import to_coding_frames

        files = pose["frames"]
        if len(files) != len(self.order):
            raise CalibrationError(
                f"{self.run / 'capture.json'}: pose {pose['name']} lists {len(files)} frames but "
                f"the coding {self.backend!r} decodes {len(self.order)} ({', '.join(self.order[:4])}"
                " …); list the pose's whole sequence.")
        frames = [read_image(self.run, rel) for rel in files]
        _check_sizes(self.run, pose, frames, self.camera_size)
        if self.layout is None:
            return frames
        return to_coding_frames(dict(zip(self.order, frames)), self.layout, self.names)

    def describe(self) -> dict[str, Any]:
        return {"backend": self.backend, "settings": self.settings, "from": "capture.json",
                **({"layout": self.layout.name} if self.layout else {})}


def solve(run_dir: Path | str, settings: dict[str, Any], pm,
          bus: EventBus | None = None) -> CalibrationResult:
    """Solve a captured calibration run (see the module docstring) and write its results, or
    refuse it (:class:`CalibrationError` with the figures) when a solve is out of bounds.

    The frames are decoded with capture.json's coding — the one they were captured with —
    whatever a profile says; the report's ``coding`` names it."""
    run = Path(run_dir)
    bus = bus or EventBus()
    cap = read_capture(run)
    board = Board(**cap["board"])
    cam_size = tuple(cap["camera_size"])
    proj_size = tuple(cap["projector_size"])
    rule = OutlierRule(settings["min_poses"], settings["outlier_factor"], settings["max_rms_px"])
    frames_of = PoseFrames(run, cap, pm)
    objp = board.object_points()
    t0 = time.perf_counter()
    free = [p for p in cap["poses"] if p["kind"] == "free"]
    turn = [p for p in cap["poses"] if p["kind"] == "turntable"]
    bus.emit(StepStarted(step="detect and decode", total=len(cap["poses"])))
    cam_poses, proj_poses, left_out, poses_report = [], [], {}, {}
    for pose in free:
        name = pose["name"]
        frames = frames_of(pose)
        white = frames_of.white(pose)
        det = detect(frames[0], board)
        rep: dict[str, Any] = {"image": white}
        poses_report[name] = rep
        if det is None:
            if pose is free[0]:  # the first pose only: a wrong count is named at once
                _refuse_other_count(frames[0], board, white)
            left_out[name] = f"target not found in {white}"
            continue
        rep["corners"] = int(len(det.ids))
        rep["sharpness_px"] = det.sharpness_px
        if det.sharpness_px > settings["max_blur_px"]:
            left_out[name] = (f"blurred: edges {det.sharpness_px:.1f} px wide > max_blur_px "
                              f"{settings['max_blur_px']:g} in {white}")
            continue
        cam_poses.append(PoseData(name, objp[det.ids], det.pixels))
        corr = frames_of.coding.decode(frames, proj_size)
        if corr.row is None:
            raise CalibrationError("projector calibration needs a coding that decodes projector "
                                   "rows too (gray code with axes = \"both\").")
        half = settings["window"] * _corner_spacing(det.pixels)
        ppx, ok = projector_corners(det.pixels, corr.column, corr.row, corr.valid, half)
        rep["projector_corners"] = int(ok.sum())
        if ok.sum() < max(6, 0.5 * len(ok)):
            left_out.setdefault(name + ":projector", f"only {int(ok.sum())} of {len(ok)} corners "
                                "decoded by the projector patterns (shadow or low contrast)")
        else:
            proj_poses.append(PoseData(name, objp[det.ids][ok], ppx[ok]))
        bus.emit(StepProgress(step="detect and decode", done=len(poses_report),
                              total=len(cap["poses"])))
    if not cam_poses:
        names = ", ".join(frames_of.white(p) for p in free) or "(no free poses)"
        raise CalibrationError(
            f"{run}: the {board.kind} ({board.columns}x{board.rows} squares) was not found in "
            f"any image: {names}. Check the target and its counts (--board COLSxROWS or "
            "[calibrate] columns and rows: squares, not inner corners), exposure and focus.")
    t1 = time.perf_counter()
    cam, proj, models, choices = solve_lenses(cam_poses, proj_poses, cam_size, proj_size,
                                              settings["distortion"], rule, left_out)
    pair = (models["camera"], models["projector"])
    stereo = calibrate_stereo(cam, proj, cam_poses, proj_poses, pair)
    joint = bundle_adjust([p for p in cam_poses if p.name in cam.per_pose_rms_px],
                          [p for p in proj_poses if p.name in proj.per_pose_rms_px],
                          stereo.camera, stereo.projector, stereo.R, stereo.T, cam.rvecs,
                          cam.tvecs, pair)
    t2 = time.perf_counter()
    axis = solve_turntable(run, turn, board, joint.camera, cam_size, settings) if turn else None
    t3 = time.perf_counter()
    rms = {"camera": cam.rms_px, "projector": proj.rms_px, "stereo": joint.rms_px}
    if axis is not None:
        rms["turntable"] = axis.rms_px
        calib = RigCalibration(joint.camera, joint.projector, joint.R, joint.T, axis.point,
                               axis.direction, source=f"dotshell calibrate ({run})", rms=rms)
    else:
        calib = RigCalibration(joint.camera, joint.projector, joint.R, joint.T,
                               np.asarray(PLACEHOLDER_AXIS_POINT, float),
                               np.asarray(PLACEHOLDER_AXIS_DIRECTION, float),
                               source=f"dotshell calibrate ({run}; no turntable axis)", rms=rms,
                               axis_measured=False)
    for name, rep in poses_report.items():
        rep["camera_rms_px"] = cam.per_pose_rms_px.get(name)
        rep["projector_rms_px"] = proj.per_pose_rms_px.get(name)
        rep["stereo_rms_px"] = joint.per_pose_rms_px.get(name)
    if axis is not None:
        for name, e in axis.per_pose_rms_px.items():
            poses_report.setdefault(name, {})["turntable_rms_px"] = e
    report: dict[str, Any] = {
        "coding": frames_of.describe(),
        "rms_px": rms,
        "turntable": (f"axis solved from {len(axis.per_pose_rms_px)} stage angles" if axis
                      else "not calibrated: no turntable frames (placeholder axis)"),
        "left_out": {"camera": cam.left_out, "projector": proj.left_out,
                     "turntable": axis.left_out if axis else {}},
        "poses": poses_report,
        "sigma": joint.sigma,
        **evidence(run, joint, models, choices, {"camera": cam_size, "projector": proj_size},
                   settings),
        "timings_s": {"detect_decode": round(t1 - t0, 3), "solve": round(t2 - t1, 3),
                      "turntable": round(t3 - t2, 3)},
    }
    truth_path = run / "ground_truth.json"
    if truth_path.is_file():
        report["ground_truth"] = compare_to_truth(calib, RigCalibration.load(truth_path))
    _publish(run, calib, report, out_of_bounds(calib, joint.sigma, axis, settings))
    return CalibrationResult(calib, report, run)


def _refuse_other_count(image: np.ndarray, board: Board, where: str) -> None:
    """Stop at once when ``image`` holds the board with one square more or fewer each way
    (inner corners counted for squares): the message names the counts that would work."""
    from dotshell.calibration.board import other_count

    other = other_count(image, board)
    if other is not None:
        raise CalibrationError(
            f"{where}: no checkerboard of {board.columns}x{board.rows} squares "
            f"({board.inner[0]}x{board.inner[1]} inner corners) in the image, but one of "
            f"{other.columns}x{other.rows} squares is: give --board {other.columns}x{other.rows} "
            f"(or [calibrate] columns = {other.columns}, rows = {other.rows}); the counts are "
            "squares, not inner corners.")


def solve_lenses(cam_poses: list[PoseData], proj_poses: list[PoseData], cam_size, proj_size,
                 distortion: str, rule: OutlierRule, left_out: dict[str, str]):
    """Camera and projector solved alone: (camera solve, projector solve, lens → model,
    lens → :class:`~dotshell.calibration.models.ModelChoice` when ``distortion`` is
    ``"auto"``). Choosing, outlier poses are judged by the richest model (a simple model's
    misfit is not a bad pose), then each lens is solved again with its chosen model.
    ``left_out`` holds the poses already left out (``name:projector`` for the projector only)."""
    first = "full" if distortion == "auto" else distortion
    cam_left = {k: v for k, v in left_out.items() if ":" not in k}
    cam = calibrate_lens("camera", cam_poses, cam_size, first, rule, cam_left)
    proj_left = {k.split(":")[0]: v for k, v in left_out.items()}
    proj_left.update({k: "left out of the camera solve" for k in cam.left_out if k not in proj_left})
    proj = calibrate_lens("projector", proj_poses, proj_size, first, rule, proj_left)
    if distortion != "auto":
        return cam, proj, {"camera": distortion, "projector": distortion}, {}
    choices, solves = {}, []
    for what, lens_solve, poses, size in (("camera", cam, cam_poses, cam_size),
                                          ("projector", proj, proj_poses, proj_size)):
        kept = [p for p in poses if p.name in lens_solve.per_pose_rms_px]
        choices[what] = choose_model(what, kept, size)
        solves.append(calibrate_lens(what, poses, size, choices[what].chosen, rule,
                                     lens_solve.left_out))
    return solves[0], solves[1], {w: c.chosen for w, c in choices.items()}, choices


def evidence(run: Path, joint, models: dict[str, str], choices: dict, sizes: dict[str, tuple],
             settings: dict[str, Any]) -> dict[str, Any]:
    """The report's evidence: the lens models (chosen and why), every coefficient with its
    one-sigma, the image coverage by corners, residual pictures per pose (``report/``) and
    the warnings that name a poorly determined parameter and its fix."""
    from dotshell.calibration.report import (coverage_pct, lens_warnings, model_summary,
                                             write_residual_pictures)

    warn_pct = settings.get("warn_sigma_pct", 0.25)
    coverage, coefficients, warnings = {}, {}, []
    for which, lens in (("camera", joint.camera), ("projector", joint.projector)):
        points = [r[which][0] for r in joint.residuals.values()]
        coverage[which] = coverage_pct(points, sizes[which])
        sig = joint.sigma[which]
        values = {"fx": lens.K[0, 0], "fy": lens.K[1, 1], "cx": lens.K[0, 2], "cy": lens.K[1, 2],
                  **dict(zip(("k1", "k2", "p1", "p2", "k3"), lens.dist))}
        coefficients[which] = {k: {"value": float(v), "sigma": sig.get(k)}
                               for k, v in values.items()}
        warnings += lens_warnings(which, lens, sig, models[which], coverage[which], warn_pct)
    (run / "report").mkdir(exist_ok=True)
    pictures = write_residual_pictures(run / "report", joint.residuals, sizes)
    return {"model": model_summary(choices, models), "coefficients": coefficients,
            "coverage_pct": coverage, "warnings": warnings,
            "residual_pictures": {n: f"report/{f}" for n, f in pictures.items()}}


def out_of_bounds(calib: RigCalibration, sigma: dict[str, Any], axis: _Axis | None,
                  settings: dict[str, Any]) -> list[str]:
    """Every figure of a solve beyond ``max_rms_px`` / ``max_sigma_pct``, each as a sentence
    that names it, its value, the bound and what would fix it."""
    max_rms, max_pct = settings["max_rms_px"], settings["max_sigma_pct"]
    out = []
    for name, value in (calib.rms or {}).items():
        if value > max_rms:
            per = ""
            if name == "turntable" and axis is not None:
                per = " (" + ", ".join(f"{n} {e:.2f} px" for n, e in axis.per_pose_rms_px.items()) + ")"
            fix = ("the stage angles do not match the images, or the board moved on the stage; "
                   "leave the turntable frames out to calibrate camera and projector alone"
                   if name == "turntable" else
                   "the images do not fit one lens (a pose moved during its sequence, or the "
                   "board is not flat)")
            out.append(f"{'turntable axis' if name == 'turntable' else name} RMS {value:.3f} px "
                       f"> max_rms_px {max_rms:g} px{per}: {fix}")
    for which, lens in (("camera", calib.camera), ("projector", calib.projector)):
        s = sigma[which]
        for key, ref in (("fx", lens.K[0, 0]), ("fy", lens.K[1, 1]), ("cx", lens.K[0, 0]),
                         ("cy", lens.K[1, 1])):
            pct = 100 * s[key] / ref
            if pct > max_pct:
                out.append(f"{which} {key} one-sigma {s[key]:.2f} px = {pct:.3f} % of the focal "
                           f"length > max_sigma_pct {max_pct:g} %: add poses that tilt the board "
                           "further and fill the field")
    pct = 100 * sigma["baseline_mm"] / calib.baseline_mm
    if pct > max_pct:
        out.append(f"baseline one-sigma {sigma['baseline_mm']:.3f} mm = {pct:.3f} % > "
                   f"max_sigma_pct {max_pct:g} %: add poses spread over the field and in depth")
    return out


def _publish(run: Path, calib: RigCalibration, report: dict[str, Any], refused: list[str]) -> None:
    """Write the calibration and its report, or — when refused — only calibration-refused.json
    with the figures, and raise."""
    from dotshell.geometry.opencv_io import write_opencv_calibration
    from dotshell.run.store import atomic_write_text, dumps

    if refused:
        report["refused"] = refused
        atomic_write_text(run / "calibration-refused.json", dumps(report))
        raise CalibrationError(
            f"{run}: calibration refused, no calibration.json written: " + "; ".join(refused)
            + f". Every figure is in {run / 'calibration-refused.json'}.")
    calib.save(run / RunLayout.CALIBRATION)
    write_opencv_calibration(calib, run / "calibration.yml")
    atomic_write_text(run / "calibration-report.json", dumps(report))
    (run / "calibration-refused.json").unlink(missing_ok=True)


@dataclass
class _Axis:
    point: np.ndarray
    direction: np.ndarray
    rms_px: float
    per_pose_rms_px: dict[str, float]
    left_out: dict[str, str]


def solve_turntable(run: Path, poses: list[dict], board: Board, camera, cam_size,
                    settings: dict[str, Any]) -> _Axis:
    """Turntable axis from the ``turntable`` poses (board detections at known stage angles)."""
    left_out: dict[str, str] = {}
    dets = []
    for pose in poses:
        img = read_image(run, pose["frames"][0])
        _check_sizes(run, {"frames": pose["frames"][:1]}, [img], cam_size)
        det = detect(img, board)
        if det is None:
            left_out[pose["name"]] = f"target not found in {pose['frames'][0]}"
            continue
        if det.sharpness_px > settings["max_blur_px"]:
            left_out[pose["name"]] = (f"blurred: edges {det.sharpness_px:.1f} px wide in "
                                      f"{pose['frames'][0]}")
            continue
        dets.append((pose, det))
    if len(dets) < 3:
        why = "; ".join(f"{n}: {r}" for n, r in left_out.items()) or "none listed"
        raise CalibrationError(
            f"turntable: {len(dets)} usable stage angles, at least 3 are needed ([calibrate] "
            f"turntable_angles_deg). Left out: {why}.")
    if board.kind == "checkerboard":
        dets = _consistent_orientation(dets, board, camera)
    objp = board.object_points()
    height = float(poses[0]["centre_mm"][2])
    while True:
        rows = [(p["name"], p["angle_deg"], d.ids, d.pixels) for p, d in dets]
        sol = turntable_axis(camera, objp, rows, board.centre, height)
        limit = settings["max_rms_px"]
        bad = {n: e for n, e in sol.per_pose_rms_px.items() if e > limit}
        if not bad or len(dets) - 1 < 3:
            break
        worst = max(bad, key=bad.__getitem__)
        left_out[worst] = f"reprojection RMS {bad[worst]:.3f} px > {limit:g} px"
        dets = [(p, d) for p, d in dets if p["name"] != worst]
    return _Axis(sol.point, sol.direction, sol.rms_px, sol.per_pose_rms_px, left_out)


def _consistent_orientation(dets, board: Board, camera):
    """A checkerboard's corner order is only defined up to a 180° turn: make every detection
    agree with the one nearest stage angle 0 (board x axes within 90°)."""
    objp = board.object_points()

    def x_axis(det):
        _, rvec, _ = cv2.solvePnP(objp[det.ids], det.pixels, camera.K, camera.dist)
        return cv2.Rodrigues(rvec)[0][:, 0]

    ref = min(dets, key=lambda pd: abs(pd[0]["angle_deg"]))
    xr = x_axis(ref[1])
    return [(p, d if x_axis(d) @ xr > 0 else flipped(d, board)) for p, d in dets]


def compare_to_truth(calib: RigCalibration, truth: RigCalibration) -> dict[str, Any]:
    """Errors of a calibration against the simulator's ground truth."""
    def lens(m, t):
        return {"fx_pct": 100 * (m.K[0, 0] / t.K[0, 0] - 1), "fy_pct": 100 * (m.K[1, 1] / t.K[1, 1] - 1),
                "cx_px": m.K[0, 2] - t.K[0, 2], "cy_px": m.K[1, 2] - t.K[1, 2],
                "k1": m.dist[0] - t.dist[0], "k2": m.dist[1] - t.dist[1],
                "p1": m.dist[2] - t.dist[2], "p2": m.dist[3] - t.dist[3]}

    dR = calib.R @ truth.R.T
    cos = np.clip((np.trace(dR) - 1) / 2, -1.0, 1.0)
    cosd = np.clip(calib.axis_direction @ truth.axis_direction, -1.0, 1.0)
    out = {
        "camera": lens(calib.camera, truth.camera),
        "projector": lens(calib.projector, truth.projector),
        "baseline_pct": 100 * (calib.baseline_mm / truth.baseline_mm - 1),
        "rotation_deg": float(np.degrees(np.arccos(cos))),
    }
    if calib.axis_measured:
        out["axis_direction_deg"] = float(np.degrees(np.arccos(cosd)))
        out.update(axis_position_errors(calib, truth))
    out = json.loads(json.dumps(out, default=float))
    out["pass"] = passes(out)
    return out


#: Height range above the plate over which the axis position is compared (mm): the samples.
AXIS_SPAN_MM = 40.0


def axis_position_errors(calib: RigCalibration, truth: RigCalibration) -> dict[str, float]:
    """Where the measured turntable axis lies against the true one.

    An axis is a line: its *position* is its perpendicular distance from the true line, which
    changes along the axis when the directions differ, so ``axis_point_mm`` is the largest
    distance over the samples' height (the true plate point to :data:`AXIS_SPAN_MM` above
    it). The plate point's slide along the axis (the height origin of the sample frame, which
    comes from the measured board-centre height, not from the images) is
    ``axis_plate_offset_mm``; ``axis_plate_point_mm`` is the plain distance between the two
    plate points.
    """
    d = calib.axis_direction / np.linalg.norm(calib.axis_direction)
    td = truth.axis_direction / np.linalg.norm(truth.axis_direction)
    dist = []
    for h in (0.0, AXIS_SPAN_MM):
        q = truth.axis_point + td * h
        v = q - calib.axis_point
        dist.append(float(np.linalg.norm(v - d * (v @ d))))
    offset = float((calib.axis_point - truth.axis_point) @ td)
    return {"axis_point_mm": max(dist), "axis_plate_offset_mm": offset,
            "axis_plate_point_mm": float(np.linalg.norm(calib.axis_point - truth.axis_point))}


def passes(err: dict[str, Any]) -> dict[str, bool]:
    """Each acceptance limit (:data:`ACCEPTANCE`) met or not."""
    a = ACCEPTANCE
    res = {}
    for which in ("camera", "projector"):
        e = err[which]
        res[f"{which}_focal"] = max(abs(e["fx_pct"]), abs(e["fy_pct"])) <= a["focal_pct"]
        res[f"{which}_principal_point"] = max(abs(e["cx_px"]), abs(e["cy_px"])) <= a["principal_px"]
    res["baseline"] = abs(err["baseline_pct"]) <= a["baseline_pct"]
    if "axis_direction_deg" in err:  # the axis was calibrated
        res["axis_direction"] = err["axis_direction_deg"] <= a["axis_direction_deg"]
        res["axis_point"] = err["axis_point_mm"] <= a["axis_point_mm"]
    if "axis_plate_offset_mm" in err:  # the plate point's slide along the axis, same limit
        res["axis_plate_offset"] = abs(err["axis_plate_offset_mm"]) <= a["axis_point_mm"]
    return res
