"""Compare the accuracy of several runs, like the paper's Table 1 and Figs. 5 and 7.

Each run's ``report.json`` gives the figures; its ``cloud.ply`` gives the per-point radius for
the plot. Writes ``validation.csv`` (one row per run) and ``validation.png`` (per run: radius
against height with the true radius dashed, and the relative error with its mean).
"""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any

import numpy as np

from dotshell.errors import RunError
from dotshell.run.layout import RunLayout
from dotshell.run.ply import read_ply
from dotshell.run.store import RunStore, atomic_write_bytes, atomic_write_text

COLUMNS = ("run", "profile", "pdi", "coding", "mean_rel_error_pct", "std_rel_error_pct",
           "rms_radius_error_mm", "points", "coverage_pct", "decoded_pct", "rejected_pct")


def run_row(store: RunStore) -> dict[str, Any]:
    """The comparison row of one run; rejected = low contrast + uncertain + row-inconsistent
    + speckle pixels, as a share of pixels that were decoded or classified uncertain / low
    contrast (i.e. saw projector light)."""
    report = store.read_json(RunLayout.REPORT)
    v = report.get("validation") or {}
    if "mean_rel_error_pct" not in v:
        v = validation_of(store)
    views = report.get("views", [])
    decoded = sum(x.get("decoded", 0) for x in views)
    rejected = sum(x.get("low_contrast", 0) + x.get("uncertain", 0) + x.get("row_rejected", 0)
                   + x.get("speckle", 0) for x in views)
    seen = decoded + sum(x.get("low_contrast", 0) + x.get("uncertain", 0) for x in views)
    manifest = store.manifest
    prof = store.read_profile()
    return {
        "run": store.root.name, "profile": report.get("profile", ""),
        "pdi": bool(prof.get("scan", {}).get("pdi", False)),
        "coding": prof.get("coding", {}).get("backend", ""),
        "mean_rel_error_pct": v["mean_rel_error_pct"], "std_rel_error_pct": v["std_rel_error_pct"],
        "rms_radius_error_mm": v["rms_radius_error_mm"], "points": v["points"],
        "coverage_pct": v["coverage_pct"],
        "decoded_pct": 100.0 * decoded / max(1, seen),
        "rejected_pct": 100.0 * rejected / max(1, seen),
        "_band": v["band_mm"], "_radius": v["true_radius_mm"], "_frames": len(manifest["frame_names"]),
    }


def validation_of(store: RunStore) -> dict[str, Any]:
    """The shape validation of a run whose report lacks it (a generation made before it was
    kept, or a report written elsewhere), measured now from its cloud and calibration, when
    its profile names the shape; RunError saying what to change otherwise."""
    from dotshell.geometry.calibration import RigCalibration
    from dotshell.pipeline.validate import cylinder_report

    prof = store.read_profile()
    v = prof.get("validation") or {}
    if v.get("shape") != "cylinder":
        raise RunError(f"{store.root}: no shape validation (its profile's [validation] shape is "
                       f"{v.get('shape', 'none')!r}); give runs scanned with [validation] shape "
                       "= \"cylinder\".")
    if not store.path(RunLayout.CLOUD).is_file():
        raise RunError(f"{store.root} has no cloud.ply to validate; make it with `dotshell "
                       "reconstruct RUN`.")
    try:
        roi = prof["processing"]["roi"]
        published = store.path(RunLayout.CURRENT, RunLayout.CALIBRATION)
        calib = RigCalibration.load(published if published.is_file()
                                    else store.path(RunLayout.CALIBRATION))
        return cylinder_report(read_ply(store.path(RunLayout.CLOUD))[0], calib, v, roi)
    except KeyError as exc:
        raise RunError(f"{store.path(RunLayout.PROFILE)} lacks {exc} needed to validate the run; "
                       "re-process it with `dotshell reconstruct RUN`.") from None


def write_csv(rows: list[dict[str, Any]], path: Path,
              columns: tuple[str, ...] = COLUMNS) -> Path:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore")
    w.writeheader()
    for r in rows:
        w.writerow({k: (f"{r[k]:.4f}" if isinstance(r.get(k), float) else r.get(k))
                    for k in columns})
    atomic_write_text(path, buf.getvalue())
    return path


def write_plot(stores: list[RunStore], rows: list[dict[str, Any]], path: Path,
               max_points: int = 40_000) -> Path:
    """Per run: radius vs height (true radius dashed) above relative error vs height."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(stores), figsize=(5 * len(stores), 6), squeeze=False,
                             sharex="col")
    rng = np.random.default_rng(0)
    for k, (store, row) in enumerate(zip(stores, rows)):
        pts, _ = read_ply(store.path(RunLayout.CLOUD))
        lo, hi = row["_band"]
        pts = pts[(pts[:, 2] >= lo) & (pts[:, 2] <= hi)]
        if len(pts) > max_points:
            pts = pts[rng.choice(len(pts), max_points, replace=False)]
        r = np.hypot(pts[:, 0], pts[:, 1])
        R = row["_radius"]
        rel = np.abs(r - R) / R * 100
        top, bottom = axes[0, k], axes[1, k]
        top.plot(pts[:, 2], r, ",", alpha=0.5)
        top.axhline(R, ls="--", color="k")
        top.set_title(f"{row['profile']}\n{row['run']}", fontsize=8)
        top.set_ylabel("radius [mm]")
        bottom.plot(pts[:, 2], rel, ",", alpha=0.5)
        bottom.axhline(row["mean_rel_error_pct"], ls="--", color="r",
                       label=f"mean {row['mean_rel_error_pct']:.2f} %")
        bottom.set_ylabel("relative error [%]")
        bottom.set_xlabel("height z [mm]")
        bottom.legend(fontsize=8)
    return save_figure(fig, path)


def save_figure(fig: Any, path: Path) -> Path:
    """Write a matplotlib figure as a PNG (atomically) and close it."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
    return path


def compare_runs(run_dirs: list[Path | str], out_dir: Path | str) -> tuple[list[dict], Path, Path]:
    """Rows for the runs, and the CSV and PNG written to ``out_dir``."""
    stores = [RunStore.open(Path(d)) for d in run_dirs]
    rows = [run_row(s) for s in stores]
    out = Path(out_dir)
    return rows, write_csv(rows, out / "validation.csv"), write_plot(stores, rows,
                                                                      out / "validation.png")
