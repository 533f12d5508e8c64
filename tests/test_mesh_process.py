"""The mesh stage's process of its own (dotshell.pipeline.mesh_process on
dotshell.runtime.child, issue 33): results and errors come back, a mesher that kills its
process is a clear MeshError, the run's recorded state stays true, and a mesher that cannot be
handed to a process is run in this one."""

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


def test_the_volume_and_its_quality_figures_start_no_numba(tmp_path):
    """The mesh process makes the volume and its quality figures without numba (its first
    compiled call costs ~0.6 s of CPU there: the boundary is sorted with numpy), and the
    figures are the kernel's: the boundary of a 20 × 10 × 30 mm box at 4 mm. A fresh process:
    this one has numba loaded."""
    import subprocess
    import sys

    code = """
import json, sys
from types import SimpleNamespace
import numpy as np
from dotshell.fem.meshes import SurfaceResult, TriangleSurface
from dotshell.pipeline.mesh import mesh_volume
from dotshell_meshing.volume import SETTINGS, TetgenVolumeMesher

corners = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], float)
surface = TriangleSurface(corners * [20.0, 10.0, 30.0], np.array(
    [[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4], [2, 6, 3], [3, 6, 7],
     [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]]))  # outward
optics = SimpleNamespace(mua_per_mm=0.01, musp_per_mm=1.0, refractive_index=1.4)
mesher = TetgenVolumeMesher({k: s.default for k, s in SETTINGS.items()})
_, volume, entry = mesh_volume(SurfaceResult(surface, {}), 0.0, 4.0, mesher, SimpleNamespace(optics=optics))
print(json.dumps({"numba": "numba" in sys.modules, "volume": entry["volume"]["volume_mm3"],
                  "boundary_faces": entry["volume"]["boundary_faces"]}))
np.save(sys.argv[1], volume.tets)
np.save(sys.argv[2], volume.boundary_faces)
"""
    tets, faces = tmp_path / "tets.npy", tmp_path / "faces.npy"
    r = subprocess.run([sys.executable, "-c", code, str(tets), str(faces)], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout.splitlines()[-1])
    assert out["numba"] is False
    assert out["volume"] == pytest.approx(20 * 10 * 30, rel=1e-9)
    from dotshell.fem.meshes import boundary_faces

    kernel = boundary_faces(np.load(tets))
    assert np.array_equal(np.load(faces), kernel) and out["boundary_faces"] == len(kernel)


def child_pid_and_module(name: str) -> tuple[int, bool]:
    import sys

    return os.getpid(), name in sys.modules


def test_a_process_started_early_imports_ahead_and_takes_the_next_job():
    """start_early: the process imports its warm-up list at once and runs the next job;
    a process started for each job otherwise (which imports nothing ahead)."""
    from dotshell.pipeline import mesh_process

    early = mesh_process.start_early(("colorsys",))
    try:
        assert mesh_process.start_early() is early  # one at a time
        pid, warmed = run_in_child(child_pid_and_module, "colorsys")
        assert pid == early.proc.pid and warmed
        pid, warmed = run_in_child(child_pid_and_module, "colorsys")
        assert pid != early.proc.pid and not warmed
    finally:
        mesh_process.discard_early()


def test_a_process_started_early_without_a_job_ends():
    from dotshell.pipeline import mesh_process

    early = mesh_process.start_early(("colorsys", "no_such_module_here", "json:no_function"))
    mesh_process.discard_early()
    assert early.proc.returncode is not None and mesh_process._early is None  # ended
    pid, _ = run_in_child(child_pid_and_module, "colorsys")  # the next job: a new process
    assert pid != early.proc.pid


def test_a_failed_warm_up_is_left_to_the_job(tmp_path):
    """A warm-up import that fails (a mesher's library missing) is no error of the process:
    the job meets it and reports it."""
    from dotshell.pipeline import mesh_process

    early = mesh_process.start_early(("no_such_module_here", "json:no_function", "colorsys"))
    try:
        pid, warmed = run_in_child(child_pid_and_module, "colorsys")
        assert pid == early.proc.pid and warmed
    finally:
        mesh_process.discard_early()


def child_meshes_and_lists_modules(job, node_distance_mm: float) -> tuple[int, list[str]]:
    import sys

    from dotshell.pipeline.mesh import mesh_cloud

    _, volume, _ = mesh_cloud(job, node_distance_mm)
    return len(volume.tets), sorted({m.split(".")[0] for m, module in sys.modules.items()
                                     if module is not None})


def test_the_mesh_process_imports_no_web_drawing_nor_scipy(small_scan, mesh_pm):
    """A mesh process as `dotshell mesh` starts it (early, its warm-up list) meshes the run's
    cloud without importing open3d's plotly drawing (dash, plotly: ~0.3 s of CPU) or scipy
    (the footprint's closing and hole filling: ~0.25 s), nor numba, nor mypy (pyvista's
    plugin for it, where mypy is installed: 0.04 s)."""
    from dotshell.pipeline import mesh_process
    from dotshell.pipeline.mesh import mesh_job
    from dotshell.pipeline.scan import load_run_profile
    from dotshell.run.store import RunStore

    mesh_process.start_early()
    store = RunStore.open(small_scan[0].run_dir)
    try:
        profile = load_run_profile(store, mesh_pm)
        d = profile.mesh.node_distance_mm
        job = mesh_job(store, profile, mesh_pm, d)
        tets, modules = run_in_child(child_meshes_and_lists_modules, job, d)
    finally:
        store.close()
        mesh_process.discard_early()
    assert tets > 1000 and {"open3d", "pyacvd", "tetgen"} <= set(modules)
    assert not {"dash", "plotly", "scipy", "numba", "mypy"} & set(modules)


class _SaysAtTeardown:
    """Writes ``path`` when the interpreter tears its module globals down."""

    def __init__(self, path: str) -> None:
        self.path = path

    def __del__(self) -> None:
        Path(self.path).write_text("torn down")


def child_keeps_an_object_till_exit(marker: str) -> int:
    import sys

    sys.modules["__main__"].kept = _SaysAtTeardown(marker)
    print("the child's last words", file=sys.stderr)
    return os.getpid()


def test_the_process_ends_without_the_interpreters_teardown(tmp_path, caplog):
    """The child writes its result and ends at once (the parent waits for its stderr to
    close): the interpreter's teardown, which frees every module's objects (0.13 s of the demo's
    mesh step), does not run; what it printed still reaches the parent's log."""
    import logging

    marker = tmp_path / "teardown"
    with caplog.at_level(logging.DEBUG, logger="dotshell.runtime.child"):
        pid = run_in_child(child_keeps_an_object_till_exit, str(marker))
    assert pid != os.getpid() and "the child's last words" in caplog.text
    assert not marker.exists()


HEAP_PROBE = """
import resource, sys
import numpy as np
from dotshell.runtime.process import fix_mmap_threshold, heap_reused

def faults_of_a_loop():
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(20):
        a = np.ones(750_000)  # 6 MB, allocated, touched and freed
        del a
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

assert fix_mmap_threshold(1 << 20)
outside = faults_of_a_loop()
with heap_reused():
    inside = faults_of_a_loop()
after = faults_of_a_loop()
print(outside, inside, after)
"""


def test_a_loop_within_heap_reused_reuses_its_memory():
    """With the command's 1 MiB mmap threshold every 6 MB array is new pages the kernel zeroes
    on first touch (up to ~1500 page faults each); within heap_reused the loop's freed blocks are
    given to its next allocations, and after it the threshold is the command's again."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", HEAP_PROBE], capture_output=True, text=True,
                         check=True).stdout
    outside, inside, after = map(int, out.split())
    assert outside > 20 * 100 and after > outside / 2  # (transparent huge pages: fewer)
    assert inside < outside / 5


def test_starting_the_mesh_process_waits_for_no_numpy():
    """`dotshell mesh` starts the mesh process first thing: the module that starts it imports
    no numpy first (0.1 s of the process's head start on the command's own start-up)."""
    import subprocess
    import sys

    probe = ("import sys; import dotshell.pipeline.mesh_process as m; "
             "print('numpy' in sys.modules, callable(m.start_early))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         check=True).stdout.split()
    assert out == ["False", "True"]


def test_dotshell_mesh_starts_the_mesh_process_before_the_cli_loads(tmp_path):
    """`dotshell mesh RUN` starts the mesh process in its entry point, before the CLI's own
    imports and parsing (~0.15-0.2 s of wall time), and ends it when the command fails before
    any job (here: no such run, exit 2); its help and other commands start none."""
    import subprocess
    import sys

    probe = (
        "import sys\n"
        "import dotshell.pipeline.mesh_process as m\n"
        "started = []\n"
        "init = m.ChildProcess.__init__\n"
        "def spy(self, *a):\n"
        "    init(self, *a)\n"
        "    started.append((self, 'dotshell.cli.app' in sys.modules))\n"
        "m.ChildProcess.__init__ = spy\n"
        "from dotshell.cli.entry import main\n"
        "code = main(sys.argv[1:])\n"
        "print('RESULT', code, [cli for _, cli in started],\n"
        "      all(p.proc.returncode is not None for p, _ in started), m._early is None)\n")
    missing = str(tmp_path / "no-such-run")
    for argv, expected in ((["mesh", missing], "RESULT 2 [False] True True"),
                           (["inspect", missing], "RESULT 2 [] True True")):
        out = subprocess.run([sys.executable, "-c", probe, *argv], capture_output=True,
                             text=True).stdout
        assert expected in out, (argv, out)
    from dotshell.cli.entry import _runs_the_mesher

    assert not _runs_the_mesher(["mesh", "--help"]) and not _runs_the_mesher(["scan", "mesh"])


def test_a_job_other_than_the_mesh_names_itself_when_its_process_dies():
    """dotshell.runtime.child serves other jobs too (the kernel compiling): a process that dies
    is a ChildProcessLost naming the job and how it ended, not the mesh's advice; an error
    raised in it carries the job's name in its note; the error crosses processes whole."""
    import pickle

    from dotshell.runtime import child

    with pytest.raises(child.ChildProcessLost,
                       match=r"the kernel compiling process ended without a result \(killed by "
                             r"SIGKILL\)") as lost:
        child.run_in_child(child_kills_itself, job="kernel compiling")
    assert "node distance" not in str(lost.value)
    again = pickle.loads(pickle.dumps(lost.value))
    assert (again.job, again.ending, str(again)) == (lost.value.job, lost.value.ending,
                                                     str(lost.value))
    with pytest.raises(ValueError) as raised:
        child.run_in_child(child_raises_value_error, job="kernel compiling")
    assert "in the kernel compiling process" in "".join(getattr(raised.value, "__notes__", []))
