"""Compare a reconstructed point cloud with a reference cloud (mm).

Two figures, both from nearest neighbours (scipy's cKDTree):

* **reconstruction → reference**, point to plane: for each reconstructed point, the distance to
  the plane fitted (PCA) to the ``k`` reference points nearest to it — the local reference
  surface, so a reference sampled more sparsely than the reconstruction does not inflate the
  figure. Points whose nearest reference point is farther than ``coverage_radius_mm`` lie
  where the reference has no surface and are counted as ``outside_reference``, not measured.
  The point-to-point distance is reported as well.
* **coverage**: the fraction of reference points that have a reconstructed point within
  ``coverage_radius_mm``, with the reference → reconstruction point-to-point distances.

References are read from ``.ply`` (as written by dotshell) or MATLAB ``.mat`` files holding an
``xyz`` array (H x W x 3 or N x 3; rows with NaN or all zeros are "no point"), as SLStudio
writes its ``pointCloud.mat``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from dotshell.errors import ReconstructionError


#: Fewest reference points a comparison can use: the local normals need neighbours.
MIN_REFERENCE_POINTS = 12


def load_reference_cloud(path: Path | str, key: str = "xyz") -> np.ndarray:
    """Reference points (N, 3) in mm from a ``.ply`` or ``.mat`` file."""
    path = Path(path)
    if not path.is_file():
        raise ReconstructionError(f"reference cloud {path} does not exist.")
    if path.suffix.lower() == ".ply":
        from dotshell.run.ply import read_ply

        pts, _ = read_ply(path, finite=False)  # clouds made elsewhere mark holes with NaN
    elif path.suffix.lower() == ".mat":
        import scipy.io

        try:
            data = scipy.io.loadmat(str(path))
        except (ValueError, NotImplementedError, OSError) as exc:
            raise ReconstructionError(f"{path}: not a readable MATLAB v5 file ({exc}); save it "
                                      "with save(..., '-v7') or export a .ply.") from None
        if key not in data:
            found = ", ".join(k for k in data if not k.startswith("__"))
            raise ReconstructionError(f"{path}: no variable {key!r} (found: {found}). The "
                                      "reference must hold the points as xyz (H x W x 3 or N x 3).")
        pts = np.asarray(data[key], np.float64)
    else:
        raise ReconstructionError(f"{path}: reference clouds must be .ply or .mat files.")
    if pts.shape[-1] != 3:
        raise ReconstructionError(f"{path}: {key} has shape {pts.shape}; expected (..., 3).")
    pts = pts.reshape(-1, 3)
    keep = np.isfinite(pts).all(axis=1) & (np.abs(pts).sum(axis=1) > 0)
    if keep.sum() < MIN_REFERENCE_POINTS:
        n = int(keep.sum())
        raise ReconstructionError(
            f"{path}: the reference cloud has {n} point{'' if n == 1 else 's'} (finite, not at "
            f"the origin); comparing needs at least {MIN_REFERENCE_POINTS} (each reference "
            "point's surface normal comes from its neighbours). Give the whole reference cloud.")
    return pts[keep]


def _local_normals(reference: np.ndarray, tree, k: int) -> np.ndarray:
    """Unit normals (N, 3) of the reference by PCA over each point's k nearest neighbours."""
    _, idx = tree.query(reference, k=k)
    nb = reference[idx]  # (N, k, 3)
    nb = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", nb, nb)
    _, vecs = np.linalg.eigh(cov)
    return vecs[:, :, 0]  # smallest eigenvalue


def compare_clouds(points: np.ndarray, reference: np.ndarray, coverage_radius_mm: float = 1.0,
                   k: int = 12) -> dict[str, Any]:
    """Distance statistics of ``points`` against ``reference`` (both (N, 3), mm)."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, np.float64).reshape(-1, 3)
    reference = np.asarray(reference, np.float64).reshape(-1, 3)
    if len(points) == 0:
        raise ReconstructionError("the reconstruction has no points to compare.")
    ref_tree = cKDTree(reference)
    d_pp, nearest = ref_tree.query(points)
    inside = d_pp <= coverage_radius_mm
    normals = _local_normals(reference, ref_tree, min(k, len(reference)))
    d_plane = np.abs(np.einsum("ij,ij->i", points - reference[nearest], normals[nearest]))
    d_ref, _ = cKDTree(points).query(reference)

    def stats(d: np.ndarray) -> dict[str, float]:
        if d.size == 0:
            return {}
        return {"median_mm": float(np.median(d)), "mean_mm": float(np.mean(d)),
                "rms_mm": float(np.sqrt(np.mean(d * d))),
                "p90_mm": float(np.percentile(d, 90)), "p95_mm": float(np.percentile(d, 95))}

    return {
        "points": int(len(points)),
        "reference_points": int(len(reference)),
        "coverage_radius_mm": float(coverage_radius_mm),
        "coverage_pct": float(100.0 * np.mean(d_ref <= coverage_radius_mm)),
        "outside_reference": int((~inside).sum()),
        "to_reference_plane": stats(d_plane[inside]),
        "to_reference_point": stats(d_pp[inside]),
        "reference_to_points": stats(d_ref),
    }
