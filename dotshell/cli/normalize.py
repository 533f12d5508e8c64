"""``dotshell normalize RUN`` (thin: calls :mod:`dotshell.pipeline.normalize` and prints its
figures)."""

from __future__ import annotations

import argparse
from typing import Any

from rich.console import Console
from rich.table import Table

from dotshell.cli.common import print_as_is

out = Console(highlight=False)
err = Console(stderr=True, highlight=False)


def masks_table(section: dict[str, Any]) -> Table:
    """Nodes used and masked (non-zero reasons) per view and source."""
    t = Table(title=f"Surface nodes per image (sin β ≥ {section['min_sin_beta']:g} used)")
    for col in ("view", "source", "used", "masked by reason"):
        t.add_column(col)
    for e in section["sources"]:
        masked = ", ".join(f"{r.replace('_', ' ')} {n}" for r, n in e["masked"].items()
                           if r != "ok" and n)
        t.add_row(f"{e['view']} ({e['angle_deg']:g}°)", e["source"], str(e["used"]), masked)
    return t


def truth_table(section: dict[str, Any]) -> Table:
    """Normalized I0 against the simulator's truth, every normalizer side by side."""
    t = Table(title="Normalized I0 vs true I0 (all images pooled)")
    for col in ("normalizer", "nodes", "median |error| [%]", "p95 |error| [%]",
                "median signed [%]"):
        t.add_column(col)
    for name, s in section["vs_truth"].items():
        label = name + (" (primary)" if name == section["normalizer"] else "")
        if not s.get("nodes"):
            t.add_row(label, "0", "", "", "")
            continue
        t.add_row(label, str(s["nodes"]), f"{s['median_abs_pct']:.2f}",
                  f"{s['p95_abs_pct']:.2f}", f"{s['median_signed_pct']:+.2f}")
    return t


def print_section(section: dict[str, Any], run_dir) -> None:
    out.print(masks_table(section))
    if "vs_truth" in section:
        out.print(truth_table(section))
    if not section["flat_field"]:
        out.print("[yellow]no flat field: camera vignetting is not corrected[/yellow]")
    print_as_is(out, f"normalized with {section['normalizer']}; files in "
                     f"{run_dir}/normalize/ (CSV, {section['vtu']}, flattened TIFF, "
                     "PNG previews)")


def cmd_normalize(args: argparse.Namespace, pm) -> int:
    from dotshell.cli.common import ScanProgress
    from dotshell.events import EventBus
    from dotshell.pipeline.commands import normalize_run

    bus = EventBus()
    bus.subscribe(ScanProgress(err))
    section = normalize_run(args.run, pm, bus, normalizer=args.normalizer,
                            min_sin_beta=args.min_sin_beta,
                            max_normal_spread_deg=args.max_normal_spread)
    print_section(section, args.run)
    return 0


def add_normalize_parser(sub, pm_factory) -> None:
    sp = sub.add_parser("normalize", help="map a run's trans-illumination frames onto its "
                        "surface and normalize them for surface orientation")
    sp.add_argument("run", help="run directory (with trans-illumination frames and surface.ply)")
    sp.add_argument("--normalizer", metavar="NAME",
                    help="normalizer backend (default: the profile's [normalizer], else "
                         "diffuse-fresnel); see `dotshell plugins`")
    sp.add_argument("--min-sin-beta", type=float, metavar="S",
                    help="grazing limit: mask nodes with sin β below S (default: the profile's "
                         "[normalize] min_sin_beta, 0.3)")
    sp.add_argument("--max-normal-spread", type=float, metavar="DEG",
                    help="mask nodes whose surface turns more than DEG degrees within their "
                         "star (default: the profile's [normalize] max_normal_spread_deg, 20; "
                         "180 = never)")
    sp.set_defaults(func=lambda a: cmd_normalize(a, pm_factory(a)))
