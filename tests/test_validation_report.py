"""The cylinder accuracy report (`dotshell.pipeline.validate.cylinder_report`) works on large
clouds a chunk at a time with few float64 temporaries (issue 33); its figures are those of the
plain one-pass arithmetic, to the last bit, whatever the chunk."""

from __future__ import annotations

import numpy as np
import pytest

from dotshell.pipeline import validate

R_MM = 12.92
SETTINGS = {"radius_mm": R_MM, "height_mm": 30.0, "edge_margin_mm": 1.0, "cell_deg": 2.0,
            "cell_mm": 1.0}
ROI = {"z_min_mm": 0.5, "z_max_mm": 40.0}


def _cloud(n: int = 40_000) -> np.ndarray:
    """float32 points (mm) on a noisy cylinder of radius R_MM, some above and below the band."""
    rng = np.random.default_rng(3)
    theta = rng.uniform(0.0, 2 * np.pi, n)
    r = R_MM + rng.normal(0.0, 0.02, n)
    z = rng.uniform(-2.0, 34.0, n)
    return np.column_stack([r * np.cos(theta), r * np.sin(theta), z]).astype(np.float32)


def _one_pass(points: np.ndarray, lo: float, hi: float) -> dict[str, float]:
    """The report's figures with every array made whole, as the definitions read."""
    z = points[:, 2].astype(np.float64)
    lateral = points[(z >= lo) & (z <= hi)]
    dr = np.hypot(lateral[:, 0], lateral[:, 1], dtype=np.float64) - R_MM
    rel = dr / R_MM
    nt = int(round(360.0 / SETTINGS["cell_deg"]))
    nz = max(1, int(np.ceil((hi - lo) / SETTINGS["cell_mm"])))
    theta = np.degrees(np.arctan2(lateral[:, 1], lateral[:, 0], dtype=np.float64)) % 360.0
    ti = np.minimum((theta / 360.0 * nt).astype(int), nt - 1)
    zi = np.minimum(((lateral[:, 2].astype(np.float64) - lo) / (hi - lo) * nz).astype(int),
                    nz - 1)
    covered = np.zeros((nt, nz), bool)
    covered[ti, zi] = True
    return {"points": len(dr), "mean_rel_error_pct": float(np.mean(np.abs(rel)) * 100),
            "std_rel_error_pct": float(np.std(np.abs(rel)) * 100),
            "mean_signed_rel_error_pct": float(np.mean(rel) * 100),
            "rms_radius_error_mm": float(np.sqrt(np.mean(np.square(dr)))),
            "p95_abs_radius_error_mm": float(np.percentile(np.abs(dr), 95)),
            "coverage_pct": float(covered.mean() * 100)}


@pytest.mark.parametrize("chunk", [997, 1 << 30])
def test_report_figures_equal_the_one_pass_arithmetic(monkeypatch, chunk):
    monkeypatch.setattr(validate, "field_band_mm", lambda calib, height_mm: (0.0, 30.0))
    monkeypatch.setattr(validate, "CHUNK_POINTS", chunk)  # rows worked on at once
    monkeypatch.setattr(validate, "FIT_SAMPLE", 5_000)
    points = _cloud()
    report = validate.cylinder_report(points, None, SETTINGS, ROI)
    lo, hi = ROI["z_min_mm"] + 1.0, 30.0 - 1.0
    expected = _one_pass(points, lo, hi)
    assert 25_000 < expected["points"] < 40_000  # the band leaves points out at both ends
    assert {k: report[k] for k in expected} == expected
    assert report["fit"]["points_used"] == 5_000
    assert abs(report["fit"]["radius_mm"] - R_MM) < 0.005
    # the merge hands the steps the cloud as columns of the PLY's bytes (strided, unaligned)
    data = np.zeros(1 + points.size // 3 * 16, np.uint8)
    table = data[1:].view(np.float32).reshape(-1, 4)
    table[:, :3] = points
    assert validate.cylinder_report(table[:, :3], None, SETTINGS, ROI) == report
