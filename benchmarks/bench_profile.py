"""The profile every benchmark uses: the reference bench, optionally scaled down for ``--quick``;
where the figures are written (:data:`RESULTS`), and a scan of it in a fresh process
(:func:`run_child`)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import tomllib
from pathlib import Path
from typing import Any

from dotshell.plugins import PluginManager
from dotshell.profile.loader import Profile, apply_overrides, validate_profile

ROOT = Path(__file__).resolve().parents[1]
PROFILE_PATH = ROOT / "profiles" / "sim-metal-cylinder.toml"

#: ``--quick``: camera and projector pixel grids × this factor (320×256 / 256×192), 2 views.
QUICK_SCALE = 0.25
QUICK_VIEWS = 2
SIM_CAPTURE_TIMEOUT_S = 900
RESULTS = ROOT / "bench-results" / "latest.json"  # --quick writes latest-quick.json


def load_bench_profile(pm: PluginManager, quick: bool) -> Profile:
    """The simulated metal-cylinder profile at full resolution, or scaled down when ``quick``.

    Scaling uses the sim plugin's :func:`dotshell_sim.bench.scale_profile` (same geometry,
    smaller pixel grids, blur kept constant in mm).
    """
    raw = tomllib.loads(PROFILE_PATH.read_text(encoding="utf-8"))
    # the simulator renders a view at its first frame: tens of seconds at full resolution on a
    # busy machine, past the default capture timeout (30 s) that guards real cameras
    raw = apply_overrides(raw, [f"camera.timeouts.capture={SIM_CAPTURE_TIMEOUT_S}"],
                          str(PROFILE_PATH))
    if quick:
        from dotshell_sim.bench import scale_profile

        raw = apply_overrides(scale_profile(raw, QUICK_SCALE), [f"scan.views={QUICK_VIEWS}"],
                              str(PROFILE_PATH))
    return validate_profile(raw, pm, str(PROFILE_PATH), PROFILE_PATH.parent)


def run_child(mode: str, path: Path, quick: bool, work: Path) -> dict[str, Any]:
    """Run ``scan_child.py`` (a fresh process) and return its figures: wall seconds, peak RSS
    (MiB, the child's own ``getrusage`` maximum) and the run's report."""
    result = work / f"{mode}_result.json"
    child = Path(__file__).resolve().parent / "scan_child.py"
    cmd = [sys.executable, str(child), mode, str(path), str(result)]
    t0 = time.perf_counter()
    subprocess.run(cmd + (["--quick"] if quick else []), check=True)
    out = json.loads(result.read_text())
    out["process_wall_s"] = time.perf_counter() - t0
    out["load"] = os.getloadavg()[0]
    return out
