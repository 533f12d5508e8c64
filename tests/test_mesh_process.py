"""The mesh stage's process of its own (dotshell.pipeline.mesh_process, issue 33): results and
errors come back, a mesher that kills its process is a clear MeshError, the run's recorded
state stays true, and a mesher that cannot be handed to a process is run in this one."""

import json
import os
import shutil
import signal
import threading
import tomllib
from pathlib import Path

import numpy as np
import pytest
import tomli_w

from dotshell import hookimpl
from dotshell.backends import Backend
from dotshell.fem.meshes import MeshError
from dotshell.pipeline.mesh_process import picklable, run_in_child
from dotshell.plugins import PluginManager

RUN_FILES = ("profile.toml", "manifest.json", "calibration.json", "cloud.ply", "report.json")


# ---- functions run in the child (module level: they are pickled by name) -----------------

def child_pid_and_sum(values: np.ndarray) -> tuple[int, float]:
    return os.getpid(), float(values.sum())


def child_raises_mesh_error() -> None:
    raise MeshError("the cloud is too sparse (said in the child)")


def child_raises_value_error() -> None:
    raise ValueError("a mesher bug")


def child_kills_itself() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


def test_the_result_comes_back_from_another_process():
    pid, total = run_in_child(child_pid_and_sum, np.arange(10.0))
    assert pid != os.getpid() and total == 45.0


def test_a_mesh_error_comes_back_as_itself():
    with pytest.raises(MeshError, match=r"too sparse \(said in the child\)"):
        run_in_child(child_raises_mesh_error)


def test_an_unexpected_error_comes_back_with_the_child_traceback():
    with pytest.raises(ValueError, match="a mesher bug") as info:
        run_in_child(child_raises_value_error)
    notes = "".join(getattr(info.value, "__notes__", []))
    assert "in the mesh process" in notes and "child_raises_value_error" in notes


def test_a_killed_child_is_a_mesh_error_naming_the_signal():
    with pytest.raises(MeshError, match=r"ended without a result \(killed by SIGKILL\)"):
        run_in_child(child_kills_itself)


# ---- the mesh stage with a mesher that dies, and with one that does not pickle ------------

class KillingSurfaceMesher:
    """A surface mesher whose process dies in surface() (as when the system kills it for lack
    of memory)."""

    def __init__(self, settings=None, context=None):
        pass

    def surface(self, points_mm, viewpoints_mm, node_distance_mm, bottom_z_mm):
        os.kill(os.getpid(), signal.SIGKILL)


class BuggySurfaceMesher:
    """A surface mesher with a bug: its ValueError must come back naming the plugin."""

    def __init__(self, settings=None, context=None):
        pass

    def surface(self, points_mm, viewpoints_mm, node_distance_mm, bottom_z_mm):
        raise ValueError(f"a bug in process {os.getpid()}")


class HereOnlySurfaceMesher:
    """A mesher holding a lock (does not pickle): it must run in the calling process."""

    def __init__(self, settings=None, context=None):
        self.lock = threading.Lock()

    def surface(self, points_mm, viewpoints_mm, node_distance_mm, bottom_z_mm):
        raise MeshError(f"surface() ran in process {os.getpid()}")


class TestMeshers:
    @hookimpl
    def dotshell_surface_meshers(self):
        return [Backend("killing", KillingSurfaceMesher, {}),
                Backend("here-only", HereOnlySurfaceMesher, {}),
                Backend("buggy", BuggySurfaceMesher, {})]


@pytest.fixture
def mesh_pm() -> PluginManager:
    pm = PluginManager()
    pm.load_entry_points()
    pm.register(TestMeshers(), name="test-meshers")
    return pm


def _run_with_mesher(small_scan, tmp_path: Path, backend: str) -> Path:
    run = tmp_path / "run"
    run.mkdir()
    for name in RUN_FILES:
        shutil.copy(small_scan[0].run_dir / name, run / name)
    prof = tomllib.loads((run / "profile.toml").read_text())
    prof["surface_mesher"] = {"backend": backend}
    prof.setdefault("mesh", {})["previews"] = False
    (run / "profile.toml").write_text(tomli_w.dumps(prof))
    return run


def test_a_mesher_killed_in_its_process_fails_the_job_and_keeps_the_run(small_scan, tmp_path,
                                                                        mesh_pm):
    from dotshell.pipeline.commands import mesh_run

    run = _run_with_mesher(small_scan, tmp_path, "killing")
    before = json.loads((run / "manifest.json").read_text())["status"]
    with pytest.raises(MeshError, match=r"mesh process ended without a result \(killed by "
                                        r"SIGKILL\).*larger node distance"):
        mesh_run(run, mesh_pm)
    m = json.loads((run / "manifest.json").read_text())
    assert m["status"] == before
    assert m["jobs"][-1]["command"] == "mesh" and m["jobs"][-1]["status"] == "failed"
    assert "killed by SIGKILL" in m["jobs"][-1]["reason"]
    assert not (run / "surface.ply").exists() and not (run / "volume.vtu").exists()


def test_a_mesher_that_does_not_pickle_runs_in_this_process(small_scan, tmp_path, mesh_pm):
    from dotshell.pipeline.commands import mesh_run

    assert not picklable(HereOnlySurfaceMesher())
    run = _run_with_mesher(small_scan, tmp_path, "here-only")
    with pytest.raises(MeshError, match=f"ran in process {os.getpid()}$"):
        mesh_run(run, mesh_pm)


def test_a_mesher_bug_in_its_process_names_the_plugin(small_scan, tmp_path, mesh_pm):
    """The mesher crosses into the mesh process with what names it (PluginObject pickles)."""
    from dotshell.errors import PluginFault
    from dotshell.pipeline.commands import mesh_run

    run = _run_with_mesher(small_scan, tmp_path, "buggy")
    with pytest.raises(PluginFault, match=r"plugin 'test-meshers' .*backend 'buggy'.* raised "
                                          r"ValueError while surface\(\): a bug in process"
                       ) as info:
        mesh_run(run, mesh_pm)
    assert f"process {os.getpid()}" not in str(info.value)


def test_the_cloud_is_mapped_not_copied_and_checked(tmp_path):
    """map_ply (what the mesh process reads): the values read_ply reads, as views of the
    file's map in float32; a non-finite point is refused naming the file."""
    from dotshell.errors import RunError
    from dotshell.run.ply import map_ply, read_ply, write_ply

    rng = np.random.default_rng(3)
    pts = rng.normal(size=(5000, 3)).astype(np.float32)
    path = write_ply(tmp_path / "cloud.ply", pts, view=rng.integers(0, 4, 5000))
    mapped, scalars = map_ply(path)
    copied, copied_scalars = read_ply(path, float_type=np.float32)
    assert mapped.dtype == np.float32
    assert not mapped.flags.owndata
    np.testing.assert_array_equal(mapped, copied)
    np.testing.assert_array_equal(scalars["view"], copied_scalars["view"])
    pts[4321, 1] = np.nan
    write_ply(path, pts, view=np.zeros(5000))
    with pytest.raises(RunError, match=r"cloud\.ply .*1 of its 5000 points have non-finite"):
        map_ply(path, chunk=1000)
