"""Polarization difference imaging (PDI): which frames a view takes, and how they combine.

With ``scan.pdi = true`` every pattern is captured twice, with the analyzer parallel and
perpendicular to the projector's polarizer (angles ``scan.pdi_angles_deg``). All patterns are
taken at the first angle, then all at the second, so a motorized analyzer moves twice per view.
Reconstruction uses ``I = |I∥ − I⊥|`` per pattern (the paper's Eq. 2): light reflected at the
surface keeps the polarization and survives the difference; light scattered below the surface
is depolarized and cancels. Camera frames are integers, so the difference is exact in the
camera's own dtype.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from dotshell.coding import PatternFrame
from dotshell.errors import RunError

SUFFIXES = ("par", "perp")


@dataclass(frozen=True)
class Shot:
    """One captured frame: which pattern, with the analyzer at which angle (None: untouched)."""

    name: str
    pattern: int
    analyzer_deg: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "pattern": self.pattern, "analyzer_deg": self.analyzer_deg}


def plan_shots(patterns: Sequence[PatternFrame], scan: Mapping[str, Any]) -> list[Shot]:
    """The frames of one view, in capture order."""
    if not scan.get("pdi"):
        return [Shot(p.name, i) for i, p in enumerate(patterns)]
    angles = scan["pdi_angles_deg"]
    return [Shot(f"{p.name}.{suffix}", i, float(angle))
            for suffix, angle in zip(SUFFIXES, angles) for i, p in enumerate(patterns)]


def shots_from_manifest(manifest: dict[str, Any]) -> list[Shot]:
    """The shot plan a run recorded (runs without PDI record plain frame names)."""
    if "shots" in manifest:
        return [Shot(s["name"], s["pattern"], s["analyzer_deg"]) for s in manifest["shots"]]
    return [Shot(n, i) for i, n in enumerate(manifest["frame_names"])]


def combine(frames: Sequence[np.ndarray] | np.ndarray, shots: Sequence[Shot]) -> list[np.ndarray]:
    """Frames in shot order → one image per pattern (|I∥ − I⊥| for PDI shots)."""
    if len(frames) != len(shots):
        raise RunError(f"{len(frames)} frames for a plan of {len(shots)} shots; the view is "
                       "incomplete.")
    n = max(s.pattern for s in shots) + 1
    by_pattern: list[list[np.ndarray]] = [[] for _ in range(n)]
    for frame, shot in zip(frames, shots):
        by_pattern[shot.pattern].append(frame)
    out = []
    for imgs in by_pattern:
        if len(imgs) == 1:
            out.append(imgs[0])
        elif len(imgs) == 2:
            out.append(difference(*imgs))
        else:
            raise RunError(f"a pattern has {len(imgs)} frames; PDI takes exactly 2.")
    return out


def difference(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """``|first − second|`` of one pattern's two frames, exact, in the first frame's dtype."""
    a, b = (np.asarray(i, np.int32) for i in (first, second))
    return np.abs(a - b).astype(first.dtype)
