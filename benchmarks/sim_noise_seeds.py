"""The simulator's sensor noise drawn two ways, over 5 seeds: the accuracy figures of the metal
cylinder and the agar cylinder (PDI) with the exact draw (Poisson shot noise, full-well clip,
normal read noise: the simulator before issue 32) and with the sensor's draw (one normal
N(λ, λ + r²) where that is nearly symmetric, :func:`dotshell_sim.render.sensor`), at reduced
resolution. Shows that the change moves the figures by less than their run-to-run noise.

Usage::

    .venv/bin/python benchmarks/sim_noise_seeds.py [--scale 0.25] [--seeds 5]

Prints, per profile and figure, mean ± std over the seeds for each draw and the difference of
the means in units of the exact draw's std; the two draws alternate seed by seed.
"""

from __future__ import annotations

import argparse
import os
import resource
import tempfile
import time
import tomllib
from pathlib import Path

import numpy as np

from dotshell.events import EventBus
from dotshell.pipeline.scan import scan
from dotshell.plugins import get_plugin_manager
from dotshell.profile.loader import validate_profile
from dotshell.runtime.process import configure_process
from dotshell_sim import devices
from dotshell_sim.bench import scale_profile
from dotshell_sim.render import SensorModel, sensor

ROOT = Path(__file__).resolve().parents[1]
PROFILES = ("sim-metal-cylinder", "sim-agar-cylinder")
FIGURES = ("mean_rel_error_pct", "std_rel_error_pct", "rms_radius_error_mm", "points")


def exact_sensor(electrons: np.ndarray, model: SensorModel, rng: np.random.Generator) -> np.ndarray:
    """The sensor as it was: Poisson shot noise for every pixel, clip, read noise, ADC."""
    e = rng.poisson(np.maximum(electrons, 0.0)).astype(np.float32)
    np.minimum(e, model.full_well_e, out=e)
    if model.read_noise_e > 0:
        e += rng.standard_normal(e.shape, dtype=np.float32) * np.float32(model.read_noise_e)
    dn = e * np.float32(model.gain_dn_per_e) + np.float32(model.dark_offset_dn)
    np.rint(dn, out=dn)
    np.clip(dn, 0, model.max_dn, out=dn)
    return dn.astype(np.uint8 if model.bit_depth <= 8 else np.uint16)


def one_scan(name: str, scale: float, seed: int, draw, pm, tmp: Path) -> tuple[dict, float]:
    """The validation figures of one scan and the CPU seconds it took."""
    raw = tomllib.loads((ROOT / "profiles" / f"{name}.toml").read_text(encoding="utf-8"))
    raw = scale_profile(raw, scale)
    raw["camera"]["settings"]["seed"] = seed
    profile = validate_profile(raw, pm, name, ROOT / "profiles")
    devices.sensor = draw
    t0 = time.process_time()
    result = scan(profile, pm, tmp / f"{name}-{seed}-{draw.__name__}", bus=EventBus())
    cpu = time.process_time() - t0
    return result.report["validation"], cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", type=float, default=0.25)
    ap.add_argument("--seeds", type=int, default=5)
    args = ap.parse_args()
    configure_process()
    pm = get_plugin_manager()
    print(f"load {os.getloadavg()[0]:.1f}; scale {args.scale}; seeds 1..{args.seeds}")
    with tempfile.TemporaryDirectory() as tmp:
        for name in PROFILES:
            figs: dict[str, list[dict]] = {"exact": [], "sensor": []}
            cpu: dict[str, list[float]] = {"exact": [], "sensor": []}
            for seed in range(1, args.seeds + 1):
                for label, draw in (("exact", exact_sensor), ("sensor", sensor)):
                    v, c = one_scan(name, args.scale, seed, draw, pm, Path(tmp))
                    figs[label].append(v)
                    cpu[label].append(c)
            print(f"\n{name}  (scan CPU s, min / median: exact "
                  f"{min(cpu['exact']):.1f} / {np.median(cpu['exact']):.1f}, sensor "
                  f"{min(cpu['sensor']):.1f} / {np.median(cpu['sensor']):.1f})")
            print(f"{'figure':<22} {'exact: mean ± std':>24} {'sensor: mean ± std':>24} "
                  f"{'Δmean / std':>12} {'Δ rel %':>8}")
            for key in FIGURES:
                a = np.array([float(v[key]) for v in figs["exact"]])
                b = np.array([float(v[key]) for v in figs["sensor"]])
                sd = a.std(ddof=1) if len(a) > 1 else float("nan")
                print(f"{key:<22} {a.mean():>13.6g} ± {sd:<8.3g} {b.mean():>13.6g} ± "
                      f"{b.std(ddof=1):<8.3g} {(b.mean() - a.mean()) / sd:>12.2f} "
                      f"{100 * (b.mean() - a.mean()) / a.mean():>8.2f}")
    print(f"\nload {os.getloadavg()[0]:.1f}; peak RSS "
          f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")


if __name__ == "__main__":
    main()
