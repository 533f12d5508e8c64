"""``dotshell mesh RUN`` and ``dotshell forward RUN`` (thin: they call
:mod:`dotshell.pipeline.mesh` and print its figures)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from dotshell.cli.common import print_as_is

out = Console(highlight=False)
err = Console(stderr=True, highlight=False)


def mesh_table(section: dict[str, Any]) -> Table:
    t = Table(title="Meshes")
    for col in ("node dist. [mm]", "dir", "surface nodes", "volume nodes", "elements",
                "Joe–Liu min / mean", "min dihedral [°]", "inverted", "volume [mm³]",
                "vs truth [%]", "time [s]"):
        t.add_column(col)
    for m in section["meshes"]:
        v = m["volume"]
        truth = m.get("validation", {}).get("volume_error_pct")
        t.add_row(f"{m['node_distance_mm']:g}", m["dir"], str(m["surface"]["vertices"]),
                  str(v["nodes"]), str(v["elements"]),
                  f"{v['joe_liu_min']:.3f} / {v['joe_liu_mean']:.3f}",
                  f"{v['min_dihedral_deg']:.1f}", str(v["inverted_elements"]),
                  f"{v['volume_mm3']:.1f}", "" if truth is None else f"{truth:+.2f}",
                  f"{m['timings_s']['surface'] + m['timings_s']['volume']:.1f}")
    return t


def cmd_mesh(args: argparse.Namespace, pm_factory) -> int:
    from dotshell.pipeline import mesh_process

    # the mesh process first: it imports the meshers while this process loads the plugins,
    # the profile and the run (two cores: ~0.3 s of the command's wall time)
    mesh_process.start_early()
    try:
        return _mesh(args, pm_factory(args))
    finally:
        mesh_process.discard_early()


def _mesh(args: argparse.Namespace, pm) -> int:
    from dotshell.cli.common import ScanProgress
    from dotshell.events import EventBus
    from dotshell.pipeline.commands import mesh_run

    bus = EventBus()
    bus.subscribe(ScanProgress(err))
    result = mesh_run(args.run, pm, bus, node_distance_mm=args.node_distance,
                      export=not args.no_export)
    out.print(mesh_table(result.report["mesh"]))
    for name, files in (result.report.get("exports") or {}).items():
        print_as_is(out, f"export {name}: {', '.join(files)}")
    print_as_is(out, f"run: {result.run_dir}")
    return 0


def cmd_forward(args: argparse.Namespace, pm) -> int:
    from dotshell.pipeline.commands import forward_run

    r = forward_run(args.run, pm, args.source, args.mesh_dir)
    b = r["boundary_fluence_per_mm2"]
    out.print(f"CW diffusion forward solution on {r['nodes']} nodes / {r['elements']} tetrahedra "
              f"(Robin A = {r['robin_A']:.3f}) in {r['solve_s']:.2f} s")
    out.print(f"source at {[round(x, 3) for x in r['source_mm']]} mm; boundary fluence "
              f"min {b['min']:.3e}, median {b['median']:.3e}, max {b['max']:.3e} /mm² per unit "
              f"power; negative nodes: {r['negative_nodes']}")
    if "detector_fluence_per_mm2" in r:
        out.print("detectors: " + ", ".join(f"{v:.3e}" for v in r["detector_fluence_per_mm2"]))
    print_as_is(out, f"fluence written to {Path(args.run) / r['file']} (point data "
                     "'fluence')")
    return 0


def add_mesh_parsers(sub, pm_factory) -> None:
    """Add the ``mesh`` and ``forward`` sub-commands; ``pm_factory(args)`` gives the plugin
    manager."""
    sp = sub.add_parser("mesh", help="surface + tetrahedral volume mesh + exports from a run's "
                        "cloud")
    sp.add_argument("run", help="run directory")
    sp.add_argument("--node-distance", type=float, metavar="MM",
                    help="node distance in mm (default: the profile's [mesh] node_distance_mm)")
    sp.add_argument("--no-export", action="store_true", help="skip the profile's exporters")
    sp.set_defaults(func=lambda a: cmd_mesh(a, pm_factory))

    sp = sub.add_parser("forward", help="CW diffusion forward solution for a point source on a "
                        "run's volume mesh")
    sp.add_argument("run", help="run directory (with volume.vtu from `dotshell mesh`)")
    sp.add_argument("--source", type=float, nargs=3, metavar=("X", "Y", "Z"),
                    help="source position in mm, sample frame (default: the first optode "
                         "source, else the mesh centroid)")
    sp.add_argument("--mesh-dir", default=".", help="mesh directory inside the run, e.g. "
                    "meshes/0.8mm (default: the run itself)")
    sp.set_defaults(func=lambda a: cmd_forward(a, pm_factory(a)))
