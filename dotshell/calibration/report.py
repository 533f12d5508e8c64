"""The calibration's evidence: image coverage by corners, residual-vector pictures per pose, and
warnings that name a poorly determined parameter with the pose that would determine it.

Pure figures (:func:`coverage_pct`, :func:`determination_warnings`) and one writer
(:func:`write_residual_pictures`, PNGs under ``<run>/report/``). Pixel quantities in pixels.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from dotshell.calibration.models import (
    COEFFICIENTS,
    MODEL_TERMS,
    radial_fold,
    undetermined_terms,
)
from dotshell.geometry.lens import Lens

#: Coverage is counted on a grid of this many cells across and down the image.
COVERAGE_GRID = 8
#: Below this share of grid cells holding a corner, the distortion is extrapolated: warn.
MIN_COVERAGE_PCT = 50.0
#: Which pose determines each intrinsic (the fix a warning names).
FIX_FOR = {
    "cx": "add a pose tilted ≥ 20° about the vertical axis (board turned left or right)",
    "cy": "add a pose tilted ≥ 20° about the horizontal axis (board leaning forward or back)",
    "fx": "add poses tilted ≥ 20° about the vertical axis and at several distances",
    "fy": "add poses tilted ≥ 20° about the horizontal axis and at several distances",
}


def coverage_pct(points: list[np.ndarray], size: tuple[int, int],
                 grid: int = COVERAGE_GRID) -> float:
    """Share (%) of a ``grid`` × ``grid`` division of the image (``size`` = width, height px)
    with at least one corner of any pose in it."""
    w, h = size
    hit = np.zeros((grid, grid), bool)
    for px in points:
        if len(px) == 0:
            continue
        i = np.clip((px[:, 0] / w * grid).astype(int), 0, grid - 1)
        j = np.clip((px[:, 1] / h * grid).astype(int), 0, grid - 1)
        hit[j, i] = True
    return float(100.0 * hit.mean())


def _simpler_model(model: str, drop: set[str]) -> str:
    """The model holding ``model``'s terms without ``drop`` (``auto`` when none does)."""
    keep = tuple(t for t in MODEL_TERMS[model] if t not in drop)
    return next((m for m, terms in MODEL_TERMS.items() if terms == keep), "auto")


def lens_warnings(which: str, lens: Lens, sigma: dict[str, float], model: str,
                  coverage: float, warn_sigma_pct: float) -> list[str]:
    """Warnings for one lens: intrinsics whose one-sigma exceeds ``warn_sigma_pct`` of the
    focal length, distortion terms not told apart from zero, a radial distortion that folds
    back inside the image, too little of the image covered by corners. Each names its fix."""
    out = []
    focal = float(lens.K[0, 0])
    for key in ("cx", "cy", "fx", "fy"):
        pct = 100.0 * sigma[key] / focal
        if pct > warn_sigma_pct:
            out.append(f"{which} {key} is poorly determined (± {sigma[key]:.2f} px = {pct:.2f} % "
                       f"of the focal length > warn_sigma_pct {warn_sigma_pct:g} %): "
                       f"{FIX_FOR[key]}")
    values = dict(zip(COEFFICIENTS, lens.dist.tolist()))
    terms = tuple(t for t in MODEL_TERMS[model] if t in sigma)
    loose = undetermined_terms(values, sigma, terms)
    if loose:
        simpler = _simpler_model(model, {s.split(" ")[0] for s in loose})
        fix = (f"solve distortion = \"{simpler}\" (without it)" if simpler != "auto" else
               "solve distortion = \"auto\" (it chooses a model these poses determine)")
        out.append(f"{which} distortion {', '.join(loose)} is not determined by these poses: "
                   f"{fix}, or add poses that put corners into the image's corners and edges")
    fold = radial_fold(lens)
    if fold:
        out.append(f"{which}: {fold}; solve a simpler model (distortion = \"auto\" chooses one)")
    if coverage < MIN_COVERAGE_PCT:
        out.append(f"{which}: corners cover only {coverage:.0f} % of the image ({COVERAGE_GRID}×"
                   f"{COVERAGE_GRID} cells): add poses with the board near the image's edges and "
                   "corners; the distortion there is extrapolated")
    return out


def _panel(size: tuple[int, int], pixels: np.ndarray, vectors: np.ndarray, scale: float,
           title: str) -> np.ndarray:
    """One device's residual vectors drawn ``scale`` times longer on a canvas about 640 px
    wide (BGR uint8)."""
    w, h = size
    zoom = 640.0 / w
    canvas = np.full((int(round(h * zoom)) + 24, 640, 3), 255, np.uint8)
    cv2.rectangle(canvas, (0, 24), (639, canvas.shape[0] - 1), (180, 180, 180), 1)
    for (x, y), (dx, dy) in zip(pixels, vectors):
        p0 = (int(round(x * zoom)), int(round(y * zoom)) + 24)
        p1 = (int(round((x + dx * scale) * zoom)), int(round((y + dy * scale) * zoom)) + 24)
        cv2.circle(canvas, p0, 1, (120, 120, 120), -1)
        cv2.arrowedLine(canvas, p0, p1, (0, 0, 200), 1, tipLength=0.25)
    cv2.putText(canvas, title, (6, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
    return canvas


def write_residual_pictures(out_dir: Path, residuals: dict[str, dict[str, tuple]],
                            sizes: dict[str, tuple[int, int]]) -> dict[str, str]:
    """One PNG per pose under ``out_dir``: camera and projector residual vectors side by side,
    all poses at one arrow scale (printed on the picture). Returns pose name → file name."""
    from dotshell.run.store import atomic_write_bytes

    lengths = [np.hypot(*v.T) for r in residuals.values() for _, v in r.values() if len(v)]
    top = float(np.percentile(np.concatenate(lengths), 99)) if lengths else 0.0
    scale = 32.0 / max(top, 1e-6) / (640.0 / max(s[0] for s in sizes.values()))
    written = {}
    for name, by_device in residuals.items():
        panels = []
        for which in [w for w in ("camera", "projector") if w in by_device]:
            px, vec = by_device[which]
            rms = float(np.sqrt(np.mean(np.sum(vec ** 2, axis=1)))) if len(vec) else float("nan")
            title = (f"{name} {which}: RMS {rms:.3f} px, {len(vec)} corners, arrows x{scale:.0f}")
            panels.append(_panel(sizes[which], px, vec, scale, title))
        height = max(p.shape[0] for p in panels)
        panels = [np.pad(p, ((0, height - p.shape[0]), (0, 0), (0, 0)), constant_values=255)
                  for p in panels]
        ok, buf = cv2.imencode(".png", np.hstack(panels))
        if ok:
            file = f"residuals_{name}.png"
            atomic_write_bytes(out_dir / file, buf.tobytes())
            written[name] = file
    return written


def model_summary(choices: dict[str, Any] | None, models: dict[str, str]) -> dict[str, Any]:
    """The report's ``model`` entry: per lens the model solved and, when chosen by held-out
    poses (``distortion = "auto"``), why and every candidate's figures."""
    out = {}
    for which, model in models.items():
        entry: dict[str, Any] = {"model": model, "terms": list(MODEL_TERMS[model])}
        if choices and which in choices:
            entry.update(choices[which].as_dict())
        else:
            entry["reason"] = "given by [calibrate] distortion"
        out[which] = entry
    return out
