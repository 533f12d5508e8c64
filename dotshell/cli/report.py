"""What the commands that finish a run print: the report's validation table (the paper's Table 1
layout), pixel losses, the cloud, the times and the previews."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rich.markup import escape

from dotshell.cli.common import out, print_as_is


def table(title: str) -> Any:
    """A rich table, imported at first use: ``--help`` and ``status`` print none."""
    from rich.table import Table

    return Table(title=title)


def print_report(report: dict[str, Any], run_dir: Path) -> None:
    """The end of a scan, resume or reprocessing: the Table 1 validation, pixel losses, the cloud,
    the times, the previews and the run's status."""
    from dotshell.pipeline.validate import table1

    rows = table1(report)
    if rows:
        t = table(title="Validation (paper's Table 1 layout)")
        t.add_column("")
        t.add_column(report.get("profile", ""))
        for k, v in rows:
            t.add_row(k, v)
        out.print(t)
    elif "validation" in report:
        out.print(f"validation: {escape(str(report['validation']))}")
    losses = pixel_losses(report.get("views") or [])
    if losses:
        out.print("pixels: " + ", ".join(f"{k} {v:.1f} %" for k, v in losses))
    cloud = report.get("cloud", {})
    print_as_is(out, f"cloud: {cloud.get('points', 0)} points → {run_dir / 'cloud.ply'}")
    timing = timing_line(report.get("timings_s") or {})
    if timing:
        out.print(timing)
    for name, rel in (report.get("previews") or {}).items():
        print_as_is(out, f"preview {name}: {run_dir / rel}")
    if "normalize" in report:
        from dotshell.cli.normalize import print_section

        print_section(report["normalize"], run_dir)
    print_as_is(out, f"run: {run_dir}  (status: {report.get('status', '?')})")


#: (timings_s key, label) of the scan's times the report prints, in the order they happen
TIMING_LABELS = (("acquire", "acquisition"), ("last_frame_to_cloud", "last frame → cloud.ply"),
                 ("merge", "merge"), ("validate", "validation"), ("previews", "previews"))


def timing_line(timings: dict[str, float]) -> str:
    """``time: acquisition 41.2 s, last frame → cloud.ply 1.3 s, ...`` from a report's
    ``timings_s`` (the keys it has; empty when it has none of them)."""
    parts = [f"{label} {timings[key]:.1f} s" for key, label in TIMING_LABELS if key in timings]
    return "time: " + ", ".join(parts) if parts else ""


#: Where a camera pixel can be lost on the way to a point, in pipeline order.
LOSS_KEYS = ("shadow", "low_contrast", "uncertain", "out_of_range", "low_modulation",
             "phase_inconsistent", "ray_outside_roi", "grazing", "row_rejected", "outside_roi",
             "speckle")


def pixel_losses(views: list[dict[str, Any]]) -> list[tuple[str, float]]:
    """(reason, share of all pixels in %) over the views: decoded and every loss, in order."""
    from dotshell.pipeline.steps import pixel_totals

    totals = pixel_totals(views)
    pixels = totals.get("pixels", 0)
    if not pixels:
        return []
    keys = ("decoded", *LOSS_KEYS, "points")
    return [(k, 100.0 * totals[k] / pixels) for k in keys if totals.get(k)]
