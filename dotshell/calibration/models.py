"""Lens-model choice: which distortion terms a camera's (or projector's) poses can determine.

Each candidate model (:data:`CANDIDATES`, simplest first) is solved on the poses; its evidence
is how well it predicts a pose it did not see (leave-one-pose-out: the lens solved from the
other poses, the left-out pose's board pose alone fitted to its corners, the RMS of those
corners' residuals in pixels). A richer model is chosen only when it predicts held-out poses
at least :data:`GAIN_NEEDED` better than every simpler one. Never chosen: a model whose radial
distortion folds back inside the image (not monotonic — no real lens does that), and one with
a term the poses do not determine (one-sigma above half its value: an over-fit whose terms
cancel each other, e.g. k2 = −500 against k3 = 60 000 in a narrow field). Every candidate's
figures are kept for the report.

Rational (k4–k6) and thin-prism terms are not candidates: :class:`~dotshell.geometry.lens.Lens`
holds OpenCV's five coefficients, which every narrow- and wide-angle lens measured here needs
at most.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from dotshell.calibration.solve import DISTORTION_FLAGS, PoseData, initial_matrix
from dotshell.geometry.lens import Lens

#: Candidate models in order of complexity (names as ``[calibrate] distortion``).
CANDIDATES = ("k1", "k1k2", "k1k2p1p2", "full")
#: Coefficients solved by each model (OpenCV order k1, k2, p1, p2, k3).
MODEL_TERMS = {"k1": ("k1",), "k1k2": ("k1", "k2"), "k1k2k3": ("k1", "k2", "k3"),
               "k1k2p1p2": ("k1", "k2", "p1", "p2"), "full": ("k1", "k2", "p1", "p2", "k3")}
COEFFICIENTS = ("k1", "k2", "p1", "p2", "k3")
#: A richer model must lower the held-out RMS by this fraction to be preferred.
GAIN_NEEDED = 0.03
_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
_SIGMA_NAMES = ("fx", "fy", "cx", "cy") + COEFFICIENTS


@dataclass
class Candidate:
    """One model solved on all poses: its fit and held-out RMS (px), lens, one-sigma values
    (``fx`` … ``k3``, px or unitless) and what is wrong with it (sentences)."""

    model: str
    fit_rms_px: float
    held_out_rms_px: float
    lens: Lens
    sigma: dict[str, float]
    non_physical: list[str] = field(default_factory=list)
    undetermined: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        coeffs = dict(zip(COEFFICIENTS, self.lens.dist.tolist()))
        return {"model": self.model, "fit_rms_px": self.fit_rms_px,
                "held_out_rms_px": self.held_out_rms_px,
                "coefficients": {k: coeffs[k] for k in MODEL_TERMS[self.model]},
                "sigma": {k: self.sigma[k] for k in MODEL_TERMS[self.model]},
                "non_physical": self.non_physical, "undetermined": self.undetermined}


@dataclass
class ModelChoice:
    """The model chosen for one lens, why, and every candidate's evidence."""

    what: str
    chosen: str
    reason: str
    candidates: list[Candidate]

    def as_dict(self) -> dict[str, Any]:
        return {"chosen": self.chosen, "reason": self.reason,
                "candidates": [c.as_dict() for c in self.candidates]}


def _calibrate(poses: list[PoseData], size: tuple[int, int], model: str, K0: np.ndarray):
    obj = [p.object_points.astype(np.float32).reshape(-1, 1, 3) for p in poses]
    img = [p.image_points.astype(np.float32).reshape(-1, 1, 2) for p in poses]
    flags = DISTORTION_FLAGS[model] | cv2.CALIB_USE_INTRINSIC_GUESS
    return cv2.calibrateCameraExtended(obj, img, size, K0.copy(), np.zeros(5), flags=flags,
                                       criteria=_CRITERIA)


def held_out_rms(poses: list[PoseData], size: tuple[int, int], model: str,
                 K0: np.ndarray) -> float:
    """Leave-one-pose-out RMS (px): each pose predicted by the lens solved from the others
    (its own board pose fitted to its corners). ``inf`` when a solve fails."""
    sq, n = 0.0, 0
    for i, held in enumerate(poses):
        rest = poses[:i] + poses[i + 1:]
        try:
            out = _calibrate(rest, size, model, K0)
            K, dist = out[1], out[2].ravel()[:5]
            ok, rvec, tvec = cv2.solvePnP(held.object_points, held.image_points, K, dist,
                                          flags=cv2.SOLVEPNP_ITERATIVE)
        except cv2.error:
            return float("inf")
        if not ok:
            return float("inf")
        px, _ = cv2.projectPoints(held.object_points, rvec, tvec, K, dist)
        e = px.reshape(-1, 2) - held.image_points
        sq += float(np.sum(e ** 2))
        n += len(e)
    return float(np.sqrt(sq / max(n, 1)))


def radial_fold(lens: Lens) -> str | None:
    """Where the lens's radial distortion stops being monotonic inside its image, as a
    sentence; ``None`` when the distorted radius grows with the ideal one over the whole image
    (what every real lens does)."""
    k1, k2, _, _, k3 = lens.dist
    K = lens.K
    w, h = lens.size
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], float)
    rd_max = float(np.max(np.hypot((corners[:, 0] - K[0, 2]) / K[0, 0],
                                   (corners[:, 1] - K[1, 2]) / K[1, 1])))
    r = np.linspace(0.0, 3.0 * rd_max, 3000)
    rd = r * (1 + k1 * r ** 2 + k2 * r ** 4 + k3 * r ** 6)
    slope = 1 + 3 * k1 * r ** 2 + 5 * k2 * r ** 4 + 7 * k3 * r ** 6
    inside = np.nonzero(rd >= rd_max)[0]
    end = inside[0] if len(inside) else len(r)
    folds = np.nonzero(slope[:end] <= 0)[0]
    if len(folds):
        where = r[folds[0]] / rd_max
        return (f"radial distortion folds back at {100 * where:.0f} % of the image's corner "
                f"radius (k1 {k1:.4g}, k2 {k2:.4g}, k3 {k3:.4g}): an over-fit, no lens does this")
    if not len(inside):
        return (f"radial distortion never reaches the image corners (k1 {k1:.4g}, k2 {k2:.4g}, "
                f"k3 {k3:.4g}): an over-fit, no lens does this")
    return None


def undetermined_terms(values: dict[str, float], sigma: dict[str, float],
                       terms: tuple[str, ...]) -> list[str]:
    """Distortion terms not told apart from zero (one-sigma above half their value), each as
    ``"k3 = 42.3 ± 31.0"``."""
    return [f"{t} = {values[t]:.4g} ± {sigma[t]:.2g}" for t in terms
            if sigma[t] > 0.5 * abs(values[t])]


def solve_candidate(poses: list[PoseData], size: tuple[int, int], model: str,
                    K0: np.ndarray) -> Candidate:
    """One model solved on all ``poses`` with its held-out RMS and its checks."""
    rms, K, dist, *_rest = _calibrate(poses, size, model, K0)
    std = np.ravel(_rest[2])
    sigma = dict(zip(_SIGMA_NAMES, std[:9].tolist()))
    lens = Lens(K, dist.ravel()[:5], *size)
    values = dict(zip(COEFFICIENTS, lens.dist.tolist()))
    fold = radial_fold(lens)
    return Candidate(model, float(rms), held_out_rms(poses, size, model, K0), lens, sigma,
                     [fold] if fold else [], undetermined_terms(values, sigma, MODEL_TERMS[model]))


def choose_model(what: str, poses: list[PoseData], size: tuple[int, int],
                 candidates: tuple[str, ...] = CANDIDATES) -> ModelChoice:
    """Solve every candidate model for ``what`` (``"camera"`` / ``"projector"``) and choose the
    simplest physical one whose held-out RMS is within :data:`GAIN_NEEDED` of the best."""
    K0 = initial_matrix(size, poses)
    solved = [solve_candidate(poses, size, m, K0) for m in candidates]
    physical = [c for c in solved if not c.non_physical and np.isfinite(c.held_out_rms_px)]
    determined = [c for c in physical if not c.undetermined]
    if not determined:
        return ModelChoice(what, candidates[0], f"no candidate has every term determined by "
                           f"these poses and a physical lens; {candidates[0]}, the simplest, is "
                           "kept (see the candidates' problems and the warnings)", solved)
    best = min(determined, key=lambda c: c.held_out_rms_px)
    chosen = next(c for c in determined
                  if c.held_out_rms_px <= best.held_out_rms_px * (1 + GAIN_NEEDED))
    return ModelChoice(what, chosen.model, _reason(chosen, best, solved), solved)


def _reason(chosen: Candidate, best: Candidate, solved: list[Candidate]) -> str:
    """Why ``chosen`` won, in one sentence naming the figures."""
    others = ", ".join(f"{c.model} {c.held_out_rms_px:.3f} px" for c in solved if c is not chosen)
    if chosen is best:
        why = f"{chosen.model} predicts held-out poses best ({chosen.held_out_rms_px:.3f} px; {others})"
    else:
        why = (f"{chosen.model} predicts held-out poses within {100 * GAIN_NEEDED:.0f} % of the "
               f"best ({chosen.held_out_rms_px:.3f} px against {best.model} "
               f"{best.held_out_rms_px:.3f} px) with fewer terms ({others})")
    folded = [c.model for c in solved if c.non_physical]
    if folded:
        why += f"; not physical, never chosen: {', '.join(folded)}"
    loose = [c.model for c in solved if c.undetermined and not c.non_physical]
    if loose:
        why += f"; terms not determined by these poses, not chosen: {', '.join(loose)}"
    return why
