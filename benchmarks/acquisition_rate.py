"""Acquisition rate of the two paths on the simulator's time model (``make bench`` section 4).

One 42-frame gray-code view of the metal-cylinder bench (projector 1024 × 768, camera pixel grid
scaled down: rendering is not part of the clock) is taken by the real runner
(:class:`dotshell.pipeline.acquire.Acquisition`) twice per display chain:

* show/settle/capture, with ``settle_ms`` measured by the latency check
  (:func:`dotshell.rig.checks.measure_latency`) on that same display chain;
* hardware-sequenced: the projector's stored sequence triggers the camera.

Both read the sim clock (:mod:`dotshell_sim.timing`): host time minus the simulator's own
computing, plus the modelled exposure (the profile's 20 ms), readout (16 ms: 1280 × 1024 at
~60 fps) and display latency, with the panel refreshing at 60 Hz. The display latency is not a
datasheet number, so the figures are given for three display chains: one refresh (a projector
on the video port with a one-frame buffer), 50 ms and 100 ms (consumer projectors' input lag).
Nothing here asserts a speed. ``python benchmarks/acquisition_rate.py`` runs it alone.
"""

from __future__ import annotations

import copy
import tomllib
from pathlib import Path
from typing import Any

from dotshell.events import EventBus
from dotshell.pipeline.acquire import Acquisition
from dotshell.plugins import PluginManager, get_plugin_manager
from dotshell.profile.loader import validate_profile
from dotshell.rig.assembly import Rig
from dotshell.rig.checks import measure_latency
from dotshell.run.store import RunStore
from dotshell_sim.bench import scale_settings

ROOT = Path(__file__).resolve().parents[1]
PROFILE = ROOT / "profiles" / "sim-metal-cylinder.toml"
READOUT_MS = 16.0
REFRESH_HZ = 60.0
LATENCIES_MS = (1000.0 / REFRESH_HZ, 50.0, 100.0)
CAMERA_SCALE = 0.1  # rendering is excluded from the clock; a small grid keeps the bench short


def timed_profile(pm: PluginManager, latency_ms: float, acquisition: str, settle_ms: float):
    raw = tomllib.loads(PROFILE.read_text())
    cam = raw["camera"]["settings"]
    raw["camera"]["settings"] = {**scale_settings(cam, "sim-camera", CAMERA_SCALE),
                                 "readout_ms": READOUT_MS, "overlap_readout": True,
                                 "supersample": 1}
    raw["projector"]["settings"].update(display_latency_ms=latency_ms, refresh_hz=REFRESH_HZ)
    raw["scan"].update(acquisition=acquisition, settle_ms=settle_ms, views=1)
    raw["outputs"] = {"previews": False}
    return validate_profile(copy.deepcopy(raw), pm, str(PROFILE), PROFILE.parent)


def time_view(pm: PluginManager, profile, work: Path) -> dict[str, Any]:
    """Sim-clock and wall seconds of one view through the runner."""
    import time

    c = profile.role("coding")
    coding = pm.create("coding", c["backend"], c["settings"], None, profile.source)
    store = RunStore.create(work, profile.name)
    with Rig(profile, pm) as rig:
        patterns = coding.patterns(rig.projector.resolution)
        store.init_manifest(profile.name, [0.0], [p.name for p in patterns])
        acq = Acquisition(rig, patterns, store, profile.data["scan"], EventBus())
        clock = rig.camera.world.clock
        rig.stage.move_to(0.0)
        t0, w0 = clock.now(), time.perf_counter()
        frames = acq.run_view(0, 0.0)
        sim_s, wall_s = clock.now() - t0, time.perf_counter() - w0
        acq.close()
        sequenced = acq.engine.name == "sequenced"
        period = getattr(acq.engine, "period_ms", None)
    store.close()
    return {"frames": len(frames), "sim_s": sim_s, "wall_s": wall_s, "sequenced": sequenced,
            "pattern_period_ms": period}


def measure(pm: PluginManager | None = None, work: Path | None = None) -> list[dict[str, Any]]:
    import tempfile

    pm = pm or get_plugin_manager()
    out = []
    with tempfile.TemporaryDirectory(prefix="dotshell-acq-") as tmp:
        work = work or Path(tmp)
        for latency in LATENCIES_MS:
            probe = timed_profile(pm, latency, "show-capture", 0.0)
            with Rig(probe, pm) as rig:
                lat = measure_latency(rig, probe.data["scan"]["exposure_ms"])
            shown = time_view(pm, timed_profile(pm, latency, "show-capture", lat.settle_ms),
                              work / f"show-{latency:.0f}")
            seq = time_view(pm, timed_profile(pm, latency, "sequenced", 0.0),
                            work / f"seq-{latency:.0f}")
            out.append({"display_latency_ms": latency, "settle_ms": lat.settle_ms,
                        "latency_seen_ms": lat.shortest_ms, "show_capture": shown,
                        "sequenced": seq, "ratio": shown["sim_s"] / seq["sim_s"]})
    return out


def print_rates(rows: list[dict[str, Any]]) -> None:
    print("\n== 4. acquisition rate, show/settle/capture vs hardware-sequenced (sim time model: "
          f"exposure 20 ms, readout {READOUT_MS:g} ms, {REFRESH_HZ:g} Hz panel) ==")
    print("  display latency | settle_ms (measured) | show/capture fps, s/view | "
          "sequenced fps, s/view (period) | ratio")
    for r in rows:
        s, q = r["show_capture"], r["sequenced"]
        print(f"  {r['display_latency_ms']:8.1f} ms     | {r['settle_ms']:6.0f} ms "
              f"({r['latency_seen_ms']:5.1f})      | {s['frames'] / s['sim_s']:6.2f}, "
              f"{s['sim_s']:5.2f} s ({s['frames']} fr) | {q['frames'] / q['sim_s']:6.2f}, "
              f"{q['sim_s']:5.2f} s ({q['pattern_period_ms']:.1f} ms) | {r['ratio']:5.1f}x")
    print("  (sim clock; host wall time per view: show/capture "
          + ", ".join(f"{r['show_capture']['wall_s']:.1f}" for r in rows) + " s, sequenced "
          + ", ".join(f"{r['sequenced']['wall_s']:.1f}" for r in rows) + " s incl. rendering)")


if __name__ == "__main__":
    print_rates(measure())
