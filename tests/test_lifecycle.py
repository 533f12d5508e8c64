"""Run lifecycle: one writer per run (a lock), true states under signals and kills, resume,
generations that never overwrite what they are based on."""

import hashlib
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import ROOT, small_profile_dict, write_profile
from dotshell.errors import RunError
from dotshell.run.frames import TiffFrameStore
from dotshell.pipeline.engine import RunJob
from dotshell.run.lifecycle import effective_status
from dotshell.run.ply import read_ply
from dotshell.run.store import RunStore

DOTSHELL = [sys.executable, "-m", "dotshell.cli.app"]


def tiny_profile(tmp_path: Path, views: int = 3, name: str = "tiny.toml", **scan) -> Path:
    """A very small bench (160x128 camera, 128x96 projector) for process-level tests."""
    raw = small_profile_dict(factor=0.125, views=views)
    raw["camera"]["settings"]["supersample"] = 1
    raw["scan"].update(scan)
    raw["outputs"] = {"previews": False}
    return write_profile(tmp_path / name, raw)


def checksums(root: Path) -> dict[str, str]:
    """Content digest of every regular file under ``root`` (links not followed twice)."""
    out = {}
    for p in sorted(root.rglob("*")):
        if p.is_file() and not p.is_symlink() and p.name not in ("events.jsonl", ".lock"):
            out[str(p.relative_to(root))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def runs_in(d: Path) -> list[Path]:
    return sorted(p for p in d.iterdir() if p.is_dir()) if d.is_dir() else []


def manifest(run: Path) -> dict:
    return json.loads((run / "manifest.json").read_text())


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted tiny scan: the cloud every interrupted-then-resumed scan must equal
    (made in this process: the command's own process is what the signal and kill tests run)."""
    from dotshell.pipeline.scan import scan
    from dotshell.plugins import PluginManager
    from dotshell.profile.loader import load_profile

    tmp = tmp_path_factory.mktemp("ref")
    prof = tiny_profile(tmp)
    pm = PluginManager()
    pm.load_entry_points()
    scan(load_profile(prof, pm), pm, tmp / "runs")
    (run,) = runs_in(tmp / "runs")
    assert manifest(run)["status"] == "completed"
    return prof, run, read_ply(run / "cloud.ply")[0]


# ---- the lock ---------------------------------------------------------------------------------

def test_a_second_writer_is_refused_with_who_holds_the_run(reference, tmp_path):
    _, run, _ = reference
    store = RunStore.open(run)
    with RunJob(store, "reconstruct"):
        other = RunJob(RunStore.open(run), "mesh")
        with pytest.raises(RunError, match=r"being written by `dotshell reconstruct` \(pid"):
            other.__enter__()
        assert RunStore.open(run).status()[0] == "running"
    assert RunStore.open(run).status() == ("completed", "")


def test_a_run_whose_writer_is_gone_is_interrupted_for_every_command(reference, tmp_path):
    _, run, _ = reference
    copy = tmp_path / "copy"
    subprocess.run(["cp", "-a", str(run), str(copy)], check=True)
    m = manifest(copy)
    m.update(status="running", job={"command": "scan", "pid": 999999})
    (copy / "manifest.json").write_text(json.dumps(m))
    status, reason = effective_status(copy, m)
    assert status == "interrupted" and "pid 999999" in reason
    out = subprocess.run([*DOTSHELL, "inspect", str(copy)], capture_output=True, text=True,
                         cwd=ROOT)
    assert out.returncode == 0 and "status: interrupted" in out.stdout


# ---- signals ----------------------------------------------------------------------------------

def _scan_process(prof: Path, out: Path) -> subprocess.Popen:
    return subprocess.Popen([*DOTSHELL, "scan", str(prof), "--out", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)


def _frames_on_disk(run: Path) -> int:
    """Frames in the run's stacks; a page the scan is writing at that instant is not readable
    yet (RunError): counted at the next look."""
    try:
        return sum(TiffFrameStore(run, int(p.stem[5:]), []).count()
                   for p in (run / "frames").glob("view_???.tif"))
    except RunError:
        return 0


def _wait_for_frames(out: Path, n: int, timeout: float = 120.0) -> Path:
    t0 = time.time()
    while time.time() - t0 < timeout:
        for run in runs_in(out):
            if _frames_on_disk(run) >= n:
                return run
        time.sleep(0.05)
    raise AssertionError(f"no run reached {n} frames in {timeout} s")


@pytest.mark.parametrize("sig,named", [(signal.SIGTERM, "SIGTERM"), (signal.SIGHUP, "SIGHUP"),
                                       (signal.SIGINT, "Ctrl-C")])
def test_a_stop_signal_marks_the_run_aborted_with_the_signal(tmp_path, sig, named):
    prof = tiny_profile(tmp_path, views=6, settle_ms=20.0)
    proc = _scan_process(prof, tmp_path / "runs")
    run = _wait_for_frames(tmp_path / "runs", 5)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    m = manifest(run)
    assert m["status"] == "aborted" and named in m["reason"], m
    assert "Traceback" not in err and "resume" in err
    store = RunStore.open(run)
    assert all(v["frames"] == store.frames(v["index"]).count() for v in m["views"])


def test_a_second_ctrl_c_while_stopping_does_not_leave_the_run_running(tmp_path):
    prof = tiny_profile(tmp_path, views=6, settle_ms=20.0)
    for _ in range(3):
        proc = _scan_process(prof, tmp_path / "runs")
        run = _wait_for_frames(tmp_path / "runs", 3)
        proc.send_signal(signal.SIGINT)
        time.sleep(0.002)
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=60)
        assert RunStore.open(run).status()[0] == "aborted"
        (tmp_path / "runs" / run.name).rename(tmp_path / f"done_{run.name}_{_}")


# ---- kills and resume -------------------------------------------------------------------------

def _scan_seconds(run: Path) -> float:
    return manifest(run)["jobs"][0]["seconds"]


def _kill_and_resume(prof: Path, out: Path, fraction: float, ref: Path,
                     ref_cloud: np.ndarray, by_frames: bool = False) -> str:
    """SIGKILL a scan ``fraction`` of the reference scan's duration after its run appeared
    (``by_frames``: once that fraction of the reference's frames is on disk, which does not
    depend on how busy the machine is), resume it, compare with the reference; returns the
    state the killed run was found in."""
    from dotshell.pipeline.scan import resume_run
    from dotshell.plugins import PluginManager

    proc = _scan_process(prof, out)
    t0 = time.time()
    while not any((r / "manifest.json").is_file() for r in runs_in(out)):
        assert time.time() - t0 < 120 and proc.poll() is None, "the scan did not start"
        time.sleep(0.01)
    if by_frames:
        _wait_for_frames(out, max(1, int(fraction * _frames_on_disk(ref))))
    else:
        time.sleep(fraction * _scan_seconds(ref))
    proc.kill()
    proc.communicate()
    (run,) = runs_in(out)
    found = RunStore.open(run).status()[0]
    assert found != "running"  # a dead writer's run is never reported running
    if found != "completed":
        pm = PluginManager()
        pm.load_entry_points()
        result = resume_run(run, pm)
        assert result.status == "completed", result.reason
    assert manifest(run)["status"] == "completed"
    cloud = read_ply(run / "cloud.ply")[0]
    assert cloud.shape == ref_cloud.shape and np.array_equal(cloud, ref_cloud), found
    return found


def test_resume_after_sigkill_gives_the_uninterrupted_cloud(reference, tmp_path):
    """Killed at 15 % and 50 % of the frames (during the capture whatever the machine's load;
    timed by the reference's seconds, a reference scanned while the machine was busier made
    both kills land after the end) and at 85 % of the reference's duration."""
    prof, ref, ref_cloud = reference
    found = [_kill_and_resume(prof, tmp_path / f"k{i}", f, ref, ref_cloud, by_frames)
             for i, (f, by_frames) in enumerate(((0.15, True), (0.5, True), (0.85, False)))]
    assert found.count("interrupted") >= 2, found


@pytest.mark.slow
def test_resume_after_sigkill_at_20_random_instants(reference, tmp_path):
    prof, ref, ref_cloud = reference
    rng = random.Random(2026)
    found = [_kill_and_resume(prof, tmp_path / f"k{i}", rng.uniform(0.0, 1.2), ref, ref_cloud)
             for i in range(20)]
    print("states found after SIGKILL:", {s: found.count(s) for s in set(found)})
    assert found.count("interrupted") >= 10


def _killed_before_calibration(ref: Path, to: Path) -> Path:
    """The state of a scan killed after its run appeared but before it saved its calibration:
    the reference run with no calibration, no frames, no products, views uncaptured."""
    subprocess.run(["cp", "-a", str(ref), str(to)], check=True)
    for name in ("calibration.json", "frames", "gen", "current"):
        p = to / name
        if p.is_symlink() or p.is_file():
            p.unlink()
        elif p.is_dir():
            shutil.rmtree(p)
    for p in to.iterdir():
        if p.is_symlink():
            p.unlink()
    m = manifest(to)
    m.update(status="running", jobs=[])
    m.pop("camera", None)
    for v in m["views"]:
        v.update(frames=0, complete=False)
    (to / "manifest.json").write_text(json.dumps(m))
    return to


def test_resume_of_a_scan_killed_before_its_calibration_starts_it_afresh(reference, tmp_path):
    from dotshell.pipeline.scan import resume_run
    from dotshell.plugins import PluginManager

    _, ref, ref_cloud = reference
    run = _killed_before_calibration(ref, tmp_path / "early")
    assert RunStore.open(run).status()[0] == "interrupted"
    pm = PluginManager()
    pm.load_entry_points()
    result = resume_run(run, pm)
    assert result.status == "completed", result.reason
    assert np.array_equal(read_ply(run / "cloud.ply")[0], ref_cloud)
    assert (run / "calibration.json").is_file()


def test_resume_refuses_frames_without_a_calibration(reference, tmp_path):
    from dotshell.cli.app import main

    _, ref, _ = reference
    run = tmp_path / "lost"
    subprocess.run(["cp", "-a", str(ref), str(run)], check=True)
    (run / "calibration.json").unlink()
    m = manifest(run)
    m["status"] = "failed"
    (run / "manifest.json").write_text(json.dumps(m))
    before = sorted(p.name for p in run.iterdir())
    assert main(["resume", str(run)]) == 2
    assert sorted(p.name for p in run.iterdir()) == before


def test_resume_refuses_a_completed_run(reference):
    from dotshell.cli.app import main

    _, run, _ = reference
    assert main(["resume", str(run)]) == 2


# ---- generations --------------------------------------------------------------------------------

def test_reprocessing_with_a_bad_calibration_changes_nothing(reference, tmp_path, capsys):
    from dotshell.cli.app import main

    _, run, _ = reference
    copy = tmp_path / "copy"
    subprocess.run(["cp", "-a", str(run), str(copy)], check=True)
    good = json.loads((copy / "calibration.json").read_text())
    bad = {
        "list": [1, 2, 3],
        "nan": {**good, "T": [float("nan"), 0, 0]},
        "zero": {**good, "T": [0, 0, 0]},
        "singular": {**good, "R": [[1, 0, 0], [0, 0, 0], [0, 0, 1]]},
        "size": {**good, "camera": {**good["camera"], "width": good["camera"]["width"] * 2}},
        "text": "not json {",
    }
    before = checksums(copy)
    for name, content in bad.items():
        f = tmp_path / f"{name}.json"
        f.write_text(content if isinstance(content, str) else json.dumps(content))
        assert main(["reconstruct", str(copy), "--calibration", str(f)]) == 2, name
        err = capsys.readouterr().err
        assert str(f) in err and "Traceback" not in err, (name, err)
        assert checksums(copy) == before, name
    assert main(["reconstruct", str(copy)]) == 0
    assert (copy / "current").resolve().name == "002"
    after = checksums(copy)
    kept = [k for k in before if k.startswith(("gen/001/", "frames/")) or k == "calibration.json"]
    stacks = [k for k in kept if k.startswith("frames/") and k.endswith(".tif")]
    assert len(stacks) == 3 and len(kept) > 10  # one frame stack per view, generation 1's files
    assert all(after[k] == before[k] for k in kept)  # frames and generation 1 untouched


def test_a_failed_reprocess_publishes_nothing_and_keeps_the_run_state(reference, tmp_path):
    from dotshell.pipeline.commands import mesh_run
    from dotshell.plugins import PluginManager

    _, run, _ = reference
    copy = tmp_path / "copy"
    subprocess.run(["cp", "-a", str(run), str(copy)], check=True)
    pm = PluginManager()
    pm.load_entry_points()
    with pytest.raises(Exception):
        mesh_run(copy, pm, node_distance_mm=float("nan"))
    m = manifest(copy)
    assert m["status"] == "completed" and (copy / "current").resolve().name == "001"
    assert m["jobs"][-1]["command"] == "mesh" and m["jobs"][-1]["status"] == "failed"
    assert "generation 1 is unchanged" in m["jobs"][-1]["reason"]


def test_files_follow_the_umask_and_orphans_are_cleaned(reference, tmp_path):
    _, run, _ = reference
    copy = tmp_path / "copy"
    subprocess.run(["cp", "-a", str(run), str(copy)], check=True)
    orphan = copy / "current" / ".cloud.ply.abc123.tmp"
    orphan.write_bytes(b"half a file")
    env = {**os.environ}
    proc = subprocess.run(["sh", "-c", f"umask 002 && exec {' '.join(DOTSHELL)} reconstruct "
                           f"{copy}"], capture_output=True, text=True, cwd=ROOT, env=env)
    assert proc.returncode == 0, proc.stderr
    assert not orphan.exists()
    mode = (copy / "current" / "cloud.ply").stat().st_mode & 0o777
    assert mode == 0o664, oct(mode)
    assert (copy / "manifest.json").stat().st_mode & 0o777 == 0o664
