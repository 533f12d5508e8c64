"""Two cameras sharing one projector that is NOT calibrated: each camera's capture sequence is
decoded through its layout, the projector codes pair the cameras' pixels, and the points come
from the two cameras' rays (:mod:`dotshell.geometry.code_stereo`), with the cameras' pair
calibration (``dotshell calibrate --camera-pair``). Writes ``cloud.ply`` (camera 1's frame,
mm) and ``report.json`` into ``<out>/<time>_camera-pair-<layout>/``.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from dotshell.errors import CalibrationError
from dotshell.pipeline.captures import CapturesResult
from dotshell.run.capture_layouts import load_layout, read_sequence
from dotshell.run.layout import RunLayout

#: Matched rays passing further apart than this (mm) are dropped (a wrong match or code).
MAX_RAY_GAP_MM = 0.2


def reconstruct_camera_pair(captures1: Path | str, captures2: Path | str,
                            pair_file: Path | str, layout1: Path | str,
                            layout2: Path | str | None, pm,
                            out_dir: Path | str = "runs") -> CapturesResult:
    """Decode both sequences, match them by projector code and triangulate camera 1 against
    camera 2; ``layout2`` defaults to ``layout1``."""
    from dotshell.calibration.camera_only import load_camera_pair
    from dotshell.geometry.code_stereo import match_by_codes, triangulate_pair
    from dotshell.run.ply import write_ply
    from dotshell.run.store import RunStore

    pair = load_camera_pair(pair_file)
    t0 = time.perf_counter()
    decoded = []
    for captures, lay, lens in ((captures1, layout1, pair.camera1),
                                (captures2, layout2 or layout1, pair.camera2)):
        layout = load_layout(lay)
        seq = read_sequence(captures, layout, pm)
        if seq.camera_size != lens.size:
            w, h = seq.camera_size
            raise CalibrationError(f"{captures}: frames are {w}x{h} px but the camera pair's "
                                   f"camera is {lens.width}x{lens.height} px ({pair_file}).")
        corr = seq.coding.decode(seq.frames, layout.projector_size)
        if corr.row is None:
            raise CalibrationError(f"{captures}: layout {layout.name!r} decodes no rows; two "
                                   "cameras are matched by projector column AND row.")
        decoded.append((layout, corr))
    t1 = time.perf_counter()
    (lay1, c1), (_, c2) = decoded
    pix1, pix2 = match_by_codes(c1.column, c1.row, c1.valid, c2.column, c2.row, c2.valid)
    points, gap = triangulate_pair(pair.camera1, pair.camera2, pair.R, pair.T, pix1, pix2)
    keep = np.isfinite(gap) & (gap <= MAX_RAY_GAP_MM) & (points[:, 2] > 0)
    t2 = time.perf_counter()
    store = RunStore.create(Path(out_dir), f"camera-pair-{lay1.name}")
    write_ply(store.path(RunLayout.CLOUD), points[keep])
    report: dict[str, Any] = {
        "captures": [str(Path(c).resolve()) for c in (captures1, captures2)],
        "camera_pair": str(Path(pair_file).resolve()), "frame": "camera 1 (mm)",
        "decode": [c1.stats, c2.stats], "matches": int(len(pix1)),
        "ray_gap_mm": {"median": float(np.median(gap)) if len(gap) else None,
                       "dropped_over": MAX_RAY_GAP_MM, "dropped": int((~keep).sum())},
        "cloud": {"path": RunLayout.CLOUD, "points": int(keep.sum())},
        "timings_s": {"read_decode": round(t1 - t0, 3), "match_triangulate": round(t2 - t1, 3)},
    }
    store.write_json(RunLayout.REPORT, report)
    store.close()
    return CapturesResult(store.root, report)
