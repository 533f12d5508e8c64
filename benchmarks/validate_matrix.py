"""Codings × PDI on the simulated agar cylinder (and the metal cylinder), for docs/light-model.md.

Runs each combination at ``--scale`` (default 0.5: 640×512 camera) with ``--views`` views and
prints a markdown table of the paper's Table 1 figures plus decoded / rejected pixel shares.
Writes the runs under ``--out`` and the table to ``bench-results/validation-matrix.md``.
"""

from __future__ import annotations

import argparse
import time
import tomllib
from pathlib import Path

from dotshell.errors import ReconstructionError
from dotshell.pipeline.compare import run_row
from dotshell.pipeline.scan import scan
from dotshell.plugins import PluginManager
from dotshell.profile.loader import validate_profile
from dotshell.run.store import RunStore, atomic_write_text
from dotshell_sim.bench import scale_profile

ROOT = Path(__file__).resolve().parents[1]
CODINGS = ("graycode", "xor04", "graycode-phase")


def cases() -> list[tuple[str, str, str, dict]]:
    """(label, profile, coding, coding settings override)."""
    out = [("metal, gray code", "sim-metal-cylinder", "graycode", {})]
    for coding in CODINGS:
        out.append((f"agar, PDI, {coding}", "sim-agar-cylinder", coding, {}))
    for coding in CODINGS:
        out.append((f"agar, no PDI, {coding}", "sim-agar-cylinder-nopdi", coding,
                    {"inverse": True, "classification": "robust"}))
    out.append(("agar, no PDI, plain thresholding", "sim-agar-cylinder-nopdi", "graycode", None))
    return out


def profile_for(name: str, coding: str, settings: dict | None, scale: float, views: int) -> dict:
    raw = tomllib.loads((ROOT / "profiles" / f"{name}.toml").read_text())
    raw = scale_profile(raw, scale)
    raw["scan"]["views"] = views
    raw["outputs"] = {"previews": False}
    if settings is not None:  # None: keep the profile's own decoder
        base = {"axes": "both"}
        if coding == "graycode":
            base.update(settings)
        raw["coding"] = {"backend": coding, "settings": base}
    return raw


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--out", default="runs/validation-matrix")
    args = ap.parse_args()
    pm = PluginManager()
    pm.load_entry_points()
    lines = [f"Scale {args.scale} (camera {round(1280 * args.scale)}×{round(1024 * args.scale)}), "
             f"{args.views} views.", "",
             "| case | mean rel. error | std | RMS µm | points | coverage | decoded | rejected | s |",
             "|---|---|---|---|---|---|---|---|---|"]
    for label, name, coding, settings in cases():
        raw = profile_for(name, coding, settings, args.scale, args.views)
        t0 = time.time()
        try:
            result = scan(validate_profile(raw, pm, label, ROOT / "profiles"), pm, args.out)
            r = run_row(RunStore.open(result.run_dir))
            lines.append(f"| {label} | {r['mean_rel_error_pct']:.3f} % | {r['std_rel_error_pct']:.3f} % | "
                         f"{r['rms_radius_error_mm'] * 1000:.1f} | {r['points']} | "
                         f"{r['coverage_pct']:.1f} % | {r['decoded_pct']:.1f} % | "
                         f"{r['rejected_pct']:.1f} % | {time.time() - t0:.0f} |")
        except ReconstructionError:  # a case that yields nothing is a result too
            lines.append(f"| {label} | no points: every pixel rejected | | | 0 | 0 % | | | "
                         f"{time.time() - t0:.0f} |")
        print(lines[-1], flush=True)
    text = "\n".join(lines) + "\n"
    print(text)
    atomic_write_text(ROOT / "bench-results" / "validation-matrix.md", text)


if __name__ == "__main__":
    main()
