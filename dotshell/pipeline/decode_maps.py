"""Decode-only output: the projector column and row seen by every camera pixel, without a
calibration (to inspect a decode, to calibrate elsewhere, or to triangulate with other tools).

For one view it writes::

    column.tiff  row.tiff     float32 (H, W) projector column / row in pixels (pixel centres at
                              integers, sub-pixel where refined), NaN where not decoded
                              (column.npy / row.npy with ``--format npy``)
    mask.png                  uint8 (H, W) reason per pixel: 0 decoded, then the codes listed in
                              the report's ``reasons`` (shadow, uncertain, out_of_range, ...)
    previews/columns.png  previews/rows.png  previews/mask.png  previews/frame.png

and a ``report.json`` with the counts per reason. :func:`decode_captures` decodes a capture
directory through its layout into ``<out>/<time>_decode-<layout>/``; :func:`decode_run` decodes
every complete view of a dotshell run into ``<out>/<time>_decode-<run>/view_NNN/`` — outside
the run, which it only reads (the run's products belong to its processing generations).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from dotshell.coding import Correspondence
from dotshell.errors import RunError
from dotshell.run.layout import RunLayout

MAP_FORMATS = ("tiff", "npy")
#: Preview colours (BGR) of the mask's reasons; unknown reasons are magenta.
REASON_COLOURS = {"decoded": (200, 200, 200), "shadow": (0, 0, 0),
                  "low_contrast": (0, 140, 255), "uncertain": (0, 200, 255),
                  "out_of_range": (0, 0, 255), "low_modulation": (255, 120, 0),
                  "phase_inconsistent": (255, 0, 160)}


@dataclass
class DecodeResult:
    """Where the maps went and the report written there."""

    out_dir: Path
    report: dict[str, Any]


def _write_bytes(path: Path, data: bytes) -> None:
    from dotshell.run.store import atomic_write_bytes

    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, data)


def write_map(path: Path, values: np.ndarray) -> Path:
    """A float32 map as TIFF (by OpenCV, 32-bit float, NaN kept) or NPY (by the suffix)."""
    values = np.ascontiguousarray(values, np.float32)
    if path.suffix == ".npy":
        import io

        buf = io.BytesIO()
        np.save(buf, values)
        _write_bytes(path, buf.getvalue())
        return path
    ok, encoded = cv2.imencode(".tiff", values)
    if not ok:
        raise RunError(f"could not encode {path.name} as a float32 TIFF.")
    _write_bytes(path, encoded.tobytes())
    return path


def read_map(path: Path | str) -> np.ndarray:
    """A map written by :func:`write_map` (float32, NaN where not decoded)."""
    path = Path(path)
    if path.suffix == ".npy":
        return np.load(path)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise RunError(f"{path} is missing or not a TIFF image.")
    return img


def mask_preview(reason: np.ndarray, names: tuple[str, ...], path: Path) -> Path:
    """The reason map in colours (:data:`REASON_COLOURS`)."""
    from dotshell.render.previews import _write_png

    lut = np.array([REASON_COLOURS.get(n, (255, 0, 255)) for n in names], np.uint8)
    return _write_png(path, lut[np.minimum(reason, len(names) - 1)])


def write_maps(directory: Path, corr: Correspondence, projector_size: tuple[int, int],
               white: np.ndarray, fmt: str = "tiff") -> dict[str, Any]:
    """Write one view's maps, mask and previews into ``directory``; returns its report entry
    (files relative to ``directory``, reason codes, counts)."""
    from dotshell.coding import label_reasons
    from dotshell.pipeline.decode_quality import view_quality
    from dotshell.render.previews import _write_png, column_map_preview, frame_preview

    if fmt not in MAP_FORMATS:
        raise RunError(f"map format {fmt!r} is not one of {', '.join(MAP_FORMATS)}.")
    directory = Path(directory)
    pdir = directory / RunLayout.PREVIEWS
    pdir.mkdir(parents=True, exist_ok=True)
    reason, names = corr.reason, corr.reason_names
    if reason is None:  # a coding that does not say why: decoded or not
        reason, names = label_reasons(corr.valid, {"not_decoded": ~corr.valid})
    files = {"column": write_map(directory / f"column.{fmt}", corr.column),
             "mask": _write_png(directory / "mask.png", reason)}
    previews = {"frame": frame_preview(white, pdir / "frame.png"),
                "columns": column_map_preview(corr.column, corr.valid, projector_size[0],
                                              pdir / "columns.png"),
                "mask": mask_preview(reason, names, pdir / "mask.png")}
    if corr.row is not None:
        files["row"] = write_map(directory / f"row.{fmt}", corr.row)
        previews["rows"] = column_map_preview(corr.row, corr.valid, projector_size[1],
                                              pdir / "rows.png")
    rel = {k: str(Path(p).relative_to(directory)) for k, p in files.items()}
    return {"files": rel,
            "previews": {k: str(Path(p).relative_to(directory)) for k, p in previews.items()},
            "reasons": dict(enumerate(names)), "counts": dict(corr.stats),
            "quality": view_quality(corr),
            "camera_size": [int(corr.valid.shape[1]), int(corr.valid.shape[0])],
            "projector_size": list(projector_size)}


def decode_captures(captures: Path | str, layout_file: Path | str, pm,
                    out_dir: Path | str = "runs", fmt: str = "tiff") -> DecodeResult:
    """Decode a capture directory through its layout (no calibration needed)."""
    from dotshell.run.capture_layouts import load_layout, read_sequence
    from dotshell.run.store import RunStore

    layout = load_layout(layout_file)
    t0 = time.perf_counter()
    seq = read_sequence(captures, layout, pm)
    t1 = time.perf_counter()
    corr = seq.coding.decode(seq.frames, layout.projector_size)
    t2 = time.perf_counter()
    store = RunStore.create(Path(out_dir), f"decode-{layout.name}")
    report = {"captures": str(Path(captures).resolve()), "layout": layout.source,
              "coding": {"backend": layout.coding, "settings": layout.coding_settings()},
              **write_maps(store.root, corr, layout.projector_size, seq.frames[0], fmt),
              "timings_s": {"read": round(t1 - t0, 3), "decode": round(t2 - t1, 3)}}
    store.write_json(RunLayout.REPORT, report)
    return DecodeResult(store.root, report)


def decode_run(run_dir: Path | str, pm, out_dir: Path | str = "runs",
               fmt: str = "tiff") -> DecodeResult:
    """Decode every complete view of a dotshell run with the run's own coding and projector
    size into a new ``<out_dir>/<time>_decode-<run name>/``: ``view_NNN/`` per view and one
    ``report.json``. The run is only read."""
    from dotshell.pipeline.pdi import combine, shots_from_manifest
    from dotshell.pipeline.scan import load_run_profile
    from dotshell.run.store import RunStore

    run = RunStore.open(Path(run_dir))
    profile = load_run_profile(run, pm)
    c = profile.required_role("coding")
    coding = pm.create("coding", c["backend"], c["settings"], None, profile.source)
    manifest = run.manifest
    shots = shots_from_manifest(manifest)
    projector_size = _projector_size(run)
    complete = [v for v in manifest["views"] if v["complete"]]
    if not complete:
        raise RunError(f"{run.root}: no view has all its frames on disk; nothing to decode.")
    out = RunStore.create(Path(out_dir), f"decode-{run.root.name}")
    views: dict[str, Any] = {}
    for v in complete:
        name = RunLayout.view_stem(v["index"])
        frames = combine(run.read_frames(v["index"]), shots)
        corr = coding.decode(frames, projector_size)
        views[name] = {"angle_deg": v["angle_deg"],
                       **write_maps(out.path(name), corr, projector_size, frames[0], fmt)}
    skipped = {RunLayout.view_stem(v["index"]): f"{v['frames']} of {len(manifest['frame_names'])} "
               "frames on disk" for v in manifest["views"] if not v["complete"]}
    report = {"run": str(run.root.resolve()),
              "coding": {"backend": c["backend"], "settings": c["settings"]},
              "views": views, "skipped": skipped}
    out.write_json(RunLayout.REPORT, report)
    return DecodeResult(out.root, report)


def _projector_size(store) -> tuple[int, int]:
    """The projector size the run's patterns were made for (its calibration.json's)."""
    from dotshell.geometry.calibration import RigCalibration

    return RigCalibration.load(store.path(RunLayout.CALIBRATION)).projector.size
