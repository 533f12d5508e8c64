"""The study table of a batch: one row per run (status, points, radius error, coverage, time),
written as ``batch.csv`` and plotted as ``batch.png``, like ``dotshell validate``'s table."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from dotshell.pipeline.batch import RunOutcome, summary_of
from dotshell.pipeline.compare import save_figure, write_csv

COLUMNS = ("run", "status", "generation", "views", "points", "mean_rel_error_pct",
           "std_rel_error_pct", "rms_radius_error_mm", "coverage_pct", "compute_s", "wall_s",
           "reason")


def study_rows(outcomes: list[RunOutcome]) -> list[dict[str, Any]]:
    """One row per run; figures of runs without a report are empty. ``compute_s``: seconds
    the run's tasks took on the workers (summed); ``wall_s``: from taking the run's lock to
    publishing (0 for a skipped run)."""
    rows = []
    for o in outcomes:
        row: dict[str, Any] = {k: None for k in COLUMNS}
        row.update(summary_of(o))
        row.update(run=o.run.name, status=o.status, reason=o.reason,
                   compute_s=round(o.compute_s, 3), wall_s=round(o.wall_s, 3))
        rows.append(row)
    return rows


def write_plot(rows: list[dict[str, Any]], path: Path) -> Path:
    """Bars per run: mean relative radius error, coverage, points, and seconds (compute and
    wall); runs without figures (failed) are marked in red."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = (("mean_rel_error_pct", "mean rel. radius error [%]"),
              ("coverage_pct", "coverage [%]"), ("points", "points"),
              ("compute_s", "time [s]"))
    x = list(range(len(rows)))
    fig, axes = plt.subplots(len(panels), 1, figsize=(max(6.0, 0.45 * len(rows) + 2), 9),
                             sharex=True, squeeze=False)
    for ax, (key, label) in zip(axes[:, 0], panels):
        vals = [r[key] if isinstance(r[key], (int, float)) else 0.0 for r in rows]
        ax.bar(x, vals, color="tab:blue", label="compute (tasks)" if key == "compute_s" else None)
        if key == "compute_s":
            ax.plot(x, [r["wall_s"] for r in rows], "k_", markersize=14, label="wall")
            ax.legend(fontsize=8)
        for i, r in enumerate(rows):
            if r["status"] not in ("completed", "skipped"):
                ax.plot(i, 0, "rx", markersize=9)
        ax.set_ylabel(label, fontsize=8)
    bottom = axes[-1, 0]
    bottom.set_xticks(x)
    bottom.set_xticklabels([f"{r['run']} ({r['status']})" for r in rows], rotation=60,
                           ha="right", fontsize=7)
    return save_figure(fig, path)


def write_study_table(outcomes: list[RunOutcome], out_dir: Path | str
                      ) -> tuple[list[dict[str, Any]], Path, Path]:
    """The rows, and ``batch.csv`` and ``batch.png`` written to ``out_dir``."""
    rows = study_rows(outcomes)
    out = Path(out_dir)
    return (rows, write_csv(rows, out / "batch.csv", COLUMNS),
            write_plot(rows, out / "batch.png"))
