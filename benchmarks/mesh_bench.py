"""`dotshell mesh` at full resolution, this tree against dotshell before issue 33's mesh work,
interleaved in one run (issues 32 and 33: the mesh step's time and peak memory).

Two clouds, each meshed at the profile's 1 mm by ``dotshell mesh`` in fresh processes:

* the metal cylinder (r = 7.7 mm): a full-resolution ``sim-metal-cylinder`` run (``--run``;
  without it one is scanned first, 3-10 min), 5.5 M points;
* an agar-like cylinder (r = 12.92 mm, 30 mm high, as ``sim-agar-cylinder``): 12 views of
  690 k points (8.3 M, the agar PDI scan's count), each on the side facing that view's camera
  (±60°) and on the top where the camera looks down on it, 0.02 mm radial noise, written with
  the metal run's calibration and manifest (the cameras of the 12 views).

The peer ("before") is the dotshell of ``--before`` (default: the commit this work started
from), exported with ``git archive`` and put first on PYTHONPATH; "after" is this tree. Each
``dotshell mesh`` runs on its own copy of the run's files; the figures: wall and CPU seconds
and the peak RSS of the process tree (``os.wait4``: the command and the mesh process it
starts), and the mesh's accuracy — volume error against the true cylinder, median radius of
the side's surface nodes against the true radius, Joe–Liu minimum, smallest dihedral angle.

    python benchmarks/mesh_bench.py [--run RUN] [--repeats 2] [--before REF] [--metal-only]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

ROOT = Path(__file__).resolve().parents[1]
#: the commit before issue 33's mesh work (voxel at half the node distance, the mesh process)
BEFORE_REF = "d7f1bf8"
RUN_FILES = ("profile.toml", "manifest.json", "calibration.json", "report.json")
AGAR_RADIUS_MM, HEIGHT_MM = 12.92, 30.0


def export_tree(ref: str, dest: Path) -> Path:
    """dotshell as of git ``ref`` (its dotshell/ and plugins/) in ``dest``."""
    dest.mkdir(parents=True)
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", ref, "dotshell", "plugins"],
                             check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    return dest


def scan_metal(out: Path) -> Path:
    """A full-resolution sim-metal-cylinder run (the shipped profile as is)."""
    subprocess.run([sys.executable, "-m", "dotshell.cli.entry", "scan", "sim-metal-cylinder",
                    "--out", str(out), "-q"], check=True, env=_env(ROOT), cwd=out.parent)
    return next(out.iterdir())


def agar_like_run(metal: Path, dest: Path, per_view: int = 690_000, seed: int = 1) -> Path:
    """A run with an agar-like cloud: the metal run's cameras, a 12.92 mm cylinder."""
    from dotshell.pipeline.mesh import ViewCentres
    from dotshell.run.ply import write_ply
    from dotshell.run.store import RunStore

    dest.mkdir(parents=True)
    for name in RUN_FILES:
        shutil.copy(metal / name, dest / name)
    prof = tomllib.loads((dest / "profile.toml").read_text())
    prof["validation"].update(radius_mm=AGAR_RADIUS_MM, height_mm=HEIGHT_MM)
    (dest / "profile.toml").write_text(tomli_w.dumps(prof))
    centres = ViewCentres.of_run(RunStore.open(dest))
    rng = np.random.default_rng(seed)
    parts, views = [], []
    for index, c in zip(centres.indices, centres.centres_mm):
        az = np.arctan2(c[1], c[0])
        n_top = per_view // 4 if c[2] > HEIGHT_MM else 0
        a = az + rng.uniform(-np.pi / 3, np.pi / 3, per_view - n_top)
        r = AGAR_RADIUS_MM + rng.normal(0, 0.02, len(a))
        side = np.column_stack([r * np.cos(a), r * np.sin(a), rng.uniform(0.5, HEIGHT_MM, len(a))])
        rt = AGAR_RADIUS_MM * np.sqrt(rng.uniform(0, 1, n_top))
        at = rng.uniform(0, 2 * np.pi, n_top)
        top = np.column_stack([rt * np.cos(at), rt * np.sin(at),
                               HEIGHT_MM + rng.normal(0, 0.02, n_top)])
        parts.append(np.concatenate([side, top]).astype(np.float32))
        views.append(np.full(per_view, index, np.float32))
    write_ply(dest / "cloud.ply", np.concatenate(parts), view=np.concatenate(views))
    return dest


#: Starts the measured command and prints its CPU seconds and peak RSS (its own or any of its
#: children's, the mesh process included: ``os.wait4``), from a small process of its own
#: between this bench (which holds the agar-like cloud) and the command.
LAUNCHER = """
import json, os, subprocess, sys
proc = subprocess.Popen(sys.argv[1:], stdout=subprocess.DEVNULL)
_, status, ru = os.wait4(proc.pid, 0)
print(json.dumps({"cpu_s": ru.ru_utime + ru.ru_stime, "peak_rss_mib": ru.ru_maxrss / 1024}))
sys.exit(os.waitstatus_to_exitcode(status))
"""


def _env(tree: Path) -> dict[str, str]:
    """The environment of a command run by the dotshell in ``tree`` (run with a working
    directory outside any source tree: ``python -m`` puts it first on ``sys.path``, before
    PYTHONPATH; from this repository's root the peer imported this tree's dotshell)."""
    return {**os.environ, "PYTHONPATH": f"{tree}:{tree / 'plugins'}", "OMP_NUM_THREADS": "1",
            "OPENBLAS_NUM_THREADS": "1"}


def mesh_once(tree: Path, run: Path, work: Path) -> dict[str, Any]:
    """``dotshell mesh`` of a private copy of ``run`` by the dotshell in ``tree``: wall, CPU and
    the process tree's peak RSS, and the mesh's accuracy."""
    copy = work / f"mesh-{time.monotonic_ns()}"
    copy.mkdir()
    for name in (*RUN_FILES, "cloud.ply"):
        shutil.copy(run / name, copy / name)
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", LAUNCHER, sys.executable, "-m",
                           "dotshell.cli.entry", "mesh", str(copy), "-q"], env=_env(tree),
                          cwd=work, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"dotshell mesh failed in {tree}: {proc.stderr}")
    usage = json.loads(proc.stdout.strip().splitlines()[-1])
    out = {"wall_s": wall, **usage, "load": os.getloadavg()[0], **accuracy(copy)}
    shutil.rmtree(copy)
    return out


def accuracy(run: Path) -> dict[str, Any]:
    from dotshell.fem.meshfiles import read_surface

    report = json.loads((run / "report.json").read_text())
    entry = report["mesh"]["meshes"][0]
    radius = tomllib.loads((run / "profile.toml").read_text())["validation"]["radius_mm"]
    v = read_surface(run / "surface.ply").vertices
    side = (v[:, 2] > 2) & (v[:, 2] < HEIGHT_MM - 2)
    return {"volume_error_pct": entry["validation"]["volume_error_pct"],
            "radius_error_mm": float(np.median(np.hypot(v[side, 0], v[side, 1])) - radius),
            "joe_liu_min": entry["volume"]["joe_liu_min"],
            "min_dihedral_deg": entry["volume"]["min_dihedral_deg"],
            "nodes": entry["volume"]["nodes"], "timings_s": entry["timings_s"]}


def spread(runs: list[dict[str, Any]], key: str) -> str:
    """Median [min-max] of ``key`` over ``runs`` (on a shared host the best alone hides the
    load's noise)."""
    values = [r[key] for r in runs]
    return f"{np.median(values):.2f} [{min(values):.2f}-{max(values):.2f}]"


def summary(runs: list[dict[str, Any]]) -> str:
    best = min(runs, key=lambda r: r["cpu_s"])
    return (f"wall {min(r['wall_s'] for r in runs):5.1f} s, CPU {best['cpu_s']:5.1f} s, peak "
            f"{min(r['peak_rss_mib'] for r in runs):5.0f} MiB | volume {best['volume_error_pct']:+.3f}"
            f" %, radius {best['radius_error_mm']:+.4f} mm, Joe-Liu min "
            f"{best['joe_liu_min']:.3f}, min dihedral {best['min_dihedral_deg']:.1f} deg, "
            f"{best['nodes']} nodes (load {best['load']:.1f})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, help="a full-resolution sim-metal-cylinder run")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--before", default=BEFORE_REF, help="git ref of the peer")
    ap.add_argument("--json", type=Path, help="write the figures here")
    ap.add_argument("--metal-only", action="store_true",
                    help="the metal cylinder run alone (issue 32's demo run), not the agar-like "
                         "cloud")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="dotshell-mesh-bench-") as tmp:
        work = Path(tmp)
        before = export_tree(args.before, work / "before")
        metal = args.run or scan_metal(work / "scan")
        clouds = {"metal cylinder": metal}
        if not args.metal_only:
            clouds["agar-like"] = agar_like_run(metal, work / "agar")
        results: dict[str, dict[str, list]] = {}
        for name, run in clouds.items():
            results[name] = {"before": [], "after": []}
            for i in range(args.repeats):
                for side in (("before", "after") if i % 2 == 0 else ("after", "before")):
                    tree = before if side == "before" else ROOT
                    results[name][side].append(mesh_once(tree, run, work))
        print(f"\n== dotshell mesh at 1 mm, full resolution: before ({args.before}) vs after, "
              f"best of {args.repeats} ==")
        for name, r in results.items():
            print(f"{name}\n  before {summary(r['before'])}\n  after  {summary(r['after'])}")
            for side in ("before", "after"):
                print(f"  {side:6s} median [range] of {len(r[side])}: wall "
                      f"{spread(r[side], 'wall_s')} s, CPU {spread(r[side], 'cpu_s')} s, load "
                      f"{spread(r[side], 'load')}")
            b, a = (min(x[k] for x in r[s]) for s in ("before", "after") for k in ("cpu_s",))
            pb = min(x["peak_rss_mib"] for x in r["before"])
            pa = min(x["peak_rss_mib"] for x in r["after"])
            print(f"  CPU {b / a:.1f}x less, peak RSS {pb - pa:.0f} MiB less "
                  f"({100 * (pb - pa) / pb:.0f} %)")
        if args.json:
            args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
