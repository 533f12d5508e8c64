"""The ground truth a simulated rig records in its runs, so that validation steps read it from
the run directory (a copied run included) instead of building the rig again.

``truth.json`` (written only when a device knows the truth)::

    {"format": "dotshell-truth/1",
     "transillumination": {"light_source": "<backend>", "units": "DN/ms ...",
                           "views": {"3": {"file": "truth/transillumination/view_003.npz",
                                           "sources": ["src_00", "src_01"]}}}}

``truth/transillumination/view_VVV.npz``: ``vertices_mm`` (V, 3) and ``triangles`` (T, 3) of
the true sample surface (sample frame), ``max_snap_mm`` and, per source ``NAME``,
``radiance_NAME`` (V,): the true I0 per vertex (:class:`dotshell.devices.SurfaceRadiance`).
Format: docs/run-directory.md.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dotshell.devices import SurfaceRadiance
from dotshell.errors import RunError
from dotshell.run.layout import RunLayout
from dotshell.run.store import RunStore, atomic_write_bytes

TRUTH_FILE = RunLayout.TRUTH
TRUTH_DIR = RunLayout.TRUTH_DIR
FORMAT = "dotshell-truth/1"
UNITS = ("camera DN per ms of exposure at the principal point, dark-subtracted and "
         "flat-fielded, from a surface element facing the camera (the paper's I0)")


def transillumination_file(view: int) -> str:
    """Where a view's true trans-illumination light goes, relative to the run."""
    return f"{TRUTH_DIR}/transillumination/view_{view:03d}.npz"


def record_transillumination_truth(store: RunStore, view: int, light_source: str,
                                   fields: dict[str, SurfaceRadiance]) -> None:
    """Write the true light of one trans-illuminated view, per source name, and list it in
    ``truth.json`` (after the arrays: the index never names a file that is not there)."""
    if not fields:
        return
    first = next(iter(fields.values()))
    arrays: dict[str, Any] = {
        "vertices_mm": np.asarray(first.vertices_mm, float),
        "triangles": np.asarray(first.triangles, np.int64),
        "max_snap_mm": np.asarray(first.max_snap_mm, float)}
    for name, field in fields.items():
        if len(field.radiance) != len(first.vertices_mm):
            raise RunError(f"{light_source}: the true light of {name!r} (view {view}) is not on "
                           "the same surface as the view's other sources.")
        arrays[f"radiance_{name}"] = np.asarray(field.radiance, float)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    rel = transillumination_file(view)
    atomic_write_bytes(store.path(rel), buf.getvalue())
    index = _read_index(store.path(TRUTH_FILE)) or {"format": FORMAT}
    entry = index.setdefault("transillumination", {"light_source": light_source,
                                                   "units": UNITS, "views": {}})
    entry["views"][str(view)] = {"file": rel, "sources": list(fields)}
    store.write_json(TRUTH_FILE, index)


def _read_index(path: Path) -> dict | None:
    try:
        index = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
        raise RunError(f"{path} is not valid JSON ({exc}); it is written by dotshell only: "
                       "restore it from a backup, or delete it to go without the truth.") from None
    if not isinstance(index, dict) or index.get("format") != FORMAT:
        raise RunError(f"{path} is not a {FORMAT} file; restore it from a backup, or delete it "
                       "to go without the truth.")
    return index


@dataclass
class TransilluminationTruthFile:
    """The true trans-illumination light a run recorded (see the module docstring)."""

    root: Path
    light_source: str
    views: dict[int, dict]

    def field(self, view: int, source: str) -> SurfaceRadiance | None:
        """The true light of ``source`` at ``view``; None if the run recorded none for it."""
        entry = self.views.get(view)
        if entry is None or source not in entry["sources"]:
            return None
        path = self.root / entry["file"]
        try:
            with np.load(path) as data:
                return SurfaceRadiance(data["vertices_mm"], data["triangles"],
                                       data[f"radiance_{source}"], float(data["max_snap_mm"]))
        except (OSError, KeyError, ValueError) as exc:
            raise RunError(f"{path} is missing or damaged ({exc}); restore it from a backup of "
                           f"the run, or delete {self.root / TRUTH_FILE} to go without the "
                           "truth.") from None


def read_transillumination_truth(run_root: Path) -> TransilluminationTruthFile | None:
    """The run's recorded true trans-illumination light; None when it has none (a real rig, or
    a run made before runs recorded it)."""
    index = _read_index(Path(run_root) / TRUTH_FILE)
    entry = (index or {}).get("transillumination")
    if not entry:
        return None
    return TransilluminationTruthFile(Path(run_root), entry["light_source"],
                                      {int(v): e for v, e in entry["views"].items()})
