"""A scan's kernels compiled before it needs them, in a process of their own (issue 33):
dotshell.pipeline.kernel_warmup."""

from __future__ import annotations

import json
import pickle
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
import tomli_w

from dotshell.events import EventBus
from dotshell.pipeline import kernel_warmup as kw

ROOT = Path(__file__).resolve().parents[1]

#: the scan, in a fresh process: the cache check forced to miss (so the scan starts the
#: compiling process, which writes its stamp); then every kernel the scan process itself
#: called, those it compiled, the stamp's kernels and the scan's messages, as JSON
SCAN_SCRIPT = r"""
import json, pickle, sys
from dotshell.cli.app import main
from dotshell.pipeline import kernel_warmup as kw
from dotshell.plugins import get_plugin_manager
from dotshell.profile.loader import load_profile

kw.cache_holds = lambda key: False
code = main(["scan", sys.argv[1], "--out", sys.argv[2]])
profile = load_profile(sys.argv[1], get_plugin_manager()).data
key = kw.warmup_key(profile, int(sys.argv[3]), get_plugin_manager())
used = kw.compiled_kernels()
stamp = pickle.loads(kw.stamp_path(key).read_bytes())
print(json.dumps({
    "exit": code,
    "used": sorted({f"{m}.{a} {s}" for m, a, s in used}),
    "compiled_here": sum(kw._misses(m, a) for m, a in {(m, a) for m, a, _ in used}),
    "stamp": sorted({f"{m}.{a} {s}" for m, a, s in stamp}),
}))
"""


def _profile(tmp_path: Path, name: str, views: int = 2) -> Path:
    from dotshell_sim.bench import scale_profile

    raw = scale_profile(tomllib.loads((ROOT / "profiles" / name).read_text()), 0.125)
    raw["scan"]["views"] = views
    raw["outputs"] = {"previews": False}
    raw["camera"]["settings"]["supersample"] = 1
    if "transillumination" in raw:
        raw["transillumination"]["views"] = [1]
        raw["light_source"]["settings"]["node_spacing_mm"] = 3.0
    if "transillumination" not in raw:
        raw.get("mesh", {})["after_scan"] = False
    else:  # meshed and normalized after the scan: the normalization's kernels too
        raw["mesh"]["node_distance_mm"] = 3.0
    path = tmp_path / "profile.toml"
    path.write_text(tomli_w.dumps(raw))
    return path


@pytest.mark.parametrize("name", ["sim-agar-cylinder.toml", "sim-metal-cylinder.toml"])
def test_the_scan_process_calls_only_kernels_compiled_before_it(tmp_path, name):
    """The agar scan (PDI, uint16 frames, the simulated laser's FEM truth, the normalization
    after it) and the metal one:
    every kernel and argument type the scan process calls is one the compiling process
    called on its synthetic view and the backends' own inputs (the stamp lists them), so on
    an empty cache the scan process compiles none itself."""
    profile = _profile(tmp_path, name)
    out = subprocess.run([sys.executable, "-c", SCAN_SCRIPT, str(profile), str(tmp_path / "runs"),
                          "12"], capture_output=True, text=True, cwd=tmp_path, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert res["exit"] == 0, out.stdout[-3000:]
    assert len(res["used"]) >= 10  # decode, refinement, solves, keep pass at least
    missing = sorted(set(res["used"]) - set(res["stamp"]))
    assert missing == [], "kernels the compiling process did not call:\n" + "\n".join(missing)
    assert res["compiled_here"] == 0
    assert "could not be compiled beforehand" not in out.stdout + out.stderr
    normalized = list((tmp_path / "runs").glob("*/gen/001/normalize"))
    assert len(normalized) == (1 if "agar" in name else 0)


def test_the_cache_check_holds_only_what_numba_s_cache_holds(tmp_path, monkeypatch):
    """A stamp is believed only as far as numba's own cache index: its kernels all cached →
    True; one signature the cache does not have, no stamp, or an unreadable one → False."""
    from numba import types

    from dotshell.pipeline.reconstruct import in_roi

    in_roi(np.zeros((4, 3)), {"radius_mm": 1.0, "z_min_mm": -1.0, "z_max_mm": 1.0})
    cached = [k for k in kw.compiled_kernels() if k[1] == "_in_cylinder"]
    assert cached
    stamps = {}
    monkeypatch.setattr(kw, "stamp_path", lambda key: stamps.setdefault(key, tmp_path / key))
    kw._write_stamp("good", cached)
    assert kw.cache_holds("good")
    never = (types.float32[:, :], types.float32, types.float32, types.float32,
             types.boolean[:], types.int64, types.int64)
    kw._write_stamp("one-missing", [*cached, ("dotshell.pipeline.reconstruct", "_in_cylinder",
                                               never)])
    assert not kw.cache_holds("one-missing")
    assert not kw.cache_holds("no-stamp")
    (tmp_path / "garbled").write_bytes(b"not a pickle")
    assert not kw.cache_holds("garbled")
    assert pickle.loads((tmp_path / "good").read_bytes()) == cached


def test_a_failed_compile_is_a_warning_and_the_scan_goes_on(tmp_path):
    """The compiling process fails (here: the run it is given does not exist): the scan is
    told, in a warning naming the cause, that its kernels are compiled where it first needs
    them; nothing is raised; a later scan of the same kind in that process is not warned
    again (a console's scans)."""
    from dotshell.plugins import get_plugin_manager

    said = []
    bus = EventBus()
    bus.subscribe(said.append)
    profile = {"coding": {"backend": "graycode", "settings": {"no-such": tmp_path.name}}}
    warmup = kw.KernelWarmup.start(tmp_path / "no-run", profile, 12, get_plugin_manager())
    warmup.wait(bus)
    texts = [(m.level, m.text) for m in said]
    assert len(texts) == 1 and texts[0][0] == "warning", texts
    assert "could not be compiled beforehand" in texts[0][1]
    assert "no-run" in texts[0][1]
    again = kw.KernelWarmup.start(tmp_path / "no-run", profile, 12, get_plugin_manager())
    again.wait(bus)  # the next scan of that kind in this process: logged, not warned again
    assert len(said) == 1


def test_the_synthetic_view_decodes_in_both_image_directions():
    """The synthetic view's left half decodes as a plane through the turntable axis (points
    in the region of interest), its right half with the projector's columns down the camera's
    rows (so the sub-pixel refinement's second pass runs); 8 and 12-bit frames."""
    from dotshell.pipeline.reconstruct import reconstruct_view
    from dotshell.pipeline.steps import make_coding
    from dotshell.plugins import get_plugin_manager
    from dotshell.profile.loader import validate_profile
    from dotshell_sim.bench import build_rig, scale_profile

    pm = get_plugin_manager()
    raw = scale_profile(tomllib.loads((ROOT / "profiles" / "sim-metal-cylinder.toml")
                                      .read_text()), 0.125)
    profile = validate_profile(raw, pm, "test", ROOT)
    calib = build_rig(raw)["camera"].ground_truth_calibration()
    coding = make_coding(profile, pm)
    patterns = [p.image for p in coding.patterns(calib.projector.size)]
    for bits, dtype in ((8, np.uint8), (12, np.uint16)):
        frames = kw.synthetic_view(calib, patterns, bits)
        assert all(f.dtype == dtype and f.shape == (calib.camera.height, calib.camera.width)
                   for f in frames)
        vc = reconstruct_view(0, 0.0, frames, coding, calib, profile.processing)
        assert vc.stats["decoded"] > 0.9 * vc.stats["pixels"], vc.stats
        assert vc.stats["refined_column"] > 0.9 * vc.stats["decoded"], vc.stats
        assert vc.stats["points"] > 0.25 * vc.stats["pixels"], vc.stats


def test_kinds_of_scan_that_call_other_kernels_have_other_stamps():
    """The stamp's key changes with what changes the kernels a scan calls (the coding's
    settings, the frame depth, trans-illumination) and not with what does not (the views)."""
    from dotshell.plugins import get_plugin_manager

    pm = get_plugin_manager()
    raw = tomllib.loads((ROOT / "profiles" / "sim-agar-cylinder.toml").read_text())
    base = kw.warmup_key(raw, 12, pm)
    assert kw.warmup_key({**raw, "scan": {**raw["scan"], "views": 3}}, 12, pm) == base
    assert kw.warmup_key(raw, 8, pm) != base
    no_trans = {**raw, "transillumination": {**raw["transillumination"], "enabled": False}}
    assert kw.warmup_key(no_trans, 12, pm) != base
    robust = {**raw, "coding": {**raw["coding"], "settings": {**raw["coding"].get("settings", {}),
                                                              "classification": "robust"}}}
    assert kw.warmup_key(robust, 12, pm) != base


#: ``dotshell reconstruct`` of a run, in a fresh process, the cache check forced to miss; then
#: the kernels that process called, the stamp the compiling process wrote and when, as JSON
RECONSTRUCT_SCRIPT = r"""
import json, os, pickle, sys, time
from pathlib import Path
from dotshell.cli.app import main
from dotshell.pipeline import kernel_warmup as kw
from dotshell.plugins import get_plugin_manager
from dotshell.run.store import RunStore

kw.cache_holds = lambda key: False
started = time.time()
code = main(["reconstruct", sys.argv[1]])
store = RunStore.open(Path(sys.argv[1]))
key = kw.warmup_key(store.read_profile(), store.manifest["camera"]["bit_depth"],
                    get_plugin_manager())
stamp = kw.stamp_path(key)
print(json.dumps({
    "exit": code,
    "used": sorted({f"{m}.{a} {s}" for m, a, s in kw.compiled_kernels()}),
    "stamp": sorted({f"{m}.{a} {s}" for m, a, s in pickle.loads(stamp.read_bytes())}),
    "stamp_new": stamp.stat().st_mtime >= started,
}))
"""


def test_reconstruct_compiles_a_missing_kernel_before_its_first_view_and_says_so(tmp_path):
    """``dotshell reconstruct`` on a cache that lacks the run's kernels: before the first view
    it tells the user it is compiling them (on an empty cache it sat silent for ~20 s) and
    the compiling process writes the stamp of the run's kind, which lists every kernel the
    reconstruct process then calls."""
    profile = _profile(tmp_path, "sim-metal-cylinder.toml")
    scan = subprocess.run([sys.executable, "-c", "import sys; from dotshell.cli.app import main; "
                           "sys.exit(main(sys.argv[1:]))", "scan", str(profile), "--out",
                           str(tmp_path / "runs")], capture_output=True, text=True, cwd=tmp_path,
                          timeout=900)
    assert scan.returncode == 0, scan.stdout[-3000:] + scan.stderr[-3000:]
    run = next((tmp_path / "runs").iterdir())
    out = subprocess.run([sys.executable, "-c", RECONSTRUCT_SCRIPT, str(run)],
                         capture_output=True, text=True, cwd=tmp_path, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert res["exit"] == 0, out.stdout[-3000:]
    told = out.stderr.replace("\n", " ")  # the progress lines
    assert told.index("compiling dotshell's kernels") < told.index("view   1:"), told[:2000]
    assert res["stamp_new"]
    assert len(res["used"]) >= 10
    missing = sorted(set(res["used"]) - set(res["stamp"]))
    assert missing == [], "kernels the compiling process did not call:\n" + "\n".join(missing)
