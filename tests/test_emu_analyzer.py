"""profiles/emu-elliptec-agar-cylinder.toml (issue 28): the simulated camera's analyzer optics
follow a real Elliptec driver on its emulator, so a PDI scan through the real analyzer driver
reconstructs the agar cylinder as the all-simulated PDI rig does (before, the simulator followed
only its own analyzer and the scan gave 0 points)."""

from __future__ import annotations

import tomllib

from conftest import ROOT, write_profile
from dotshell.pipeline.scan import scan
from dotshell.profile.loader import load_profile
from dotshell_sim.bench import scale_profile


def tiny(name: str, **changes) -> dict:
    raw = scale_profile(tomllib.loads((ROOT / "profiles" / f"{name}.toml").read_text()), 0.125)
    raw["camera"]["settings"]["supersample"] = 1
    raw["scan"]["views"] = 2
    raw["outputs"] = {"previews": False}
    raw.pop("transillumination", None)
    raw.pop("light_source", None)
    raw.pop("mesh", None)
    raw.pop("normalize", None)
    raw.pop("normalizer", None)
    for section, keys in changes.items():
        raw[section]["settings"].update(keys)
    return raw


def test_a_pdi_scan_through_the_elliptec_emulator_matches_the_simulated_analyzer(
        tmp_path, dotshell_pm, serial_emulator):
    emu = serial_emulator("elliptec", speed_deg_s=720.0)
    mixed = load_profile(write_profile(tmp_path / "emu.toml", tiny(
        "emu-elliptec-agar-cylinder", analyzer={"port": emu.port})), dotshell_pm)
    simulated = load_profile(write_profile(tmp_path / "sim.toml", tiny("sim-agar-cylinder")),
                             dotshell_pm)
    got = scan(mixed, dotshell_pm, tmp_path / "emu")
    ref = scan(simulated, dotshell_pm, tmp_path / "sim")
    assert got.status == ref.status == "completed"
    points, ref_points = got.report["cloud"]["points"], ref.report["cloud"]["points"]
    assert points > 0.9 * ref_points > 0
    v, r = got.report["validation"], ref.report["validation"]
    assert abs(v["mean_rel_error_pct"] - r["mean_rel_error_pct"]) < 0.1
    moves = [c for _, c in emu.commands if c.startswith("ma")]
    assert len(moves) >= 2  # parallel and crossed, set by the driver
