import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


@pytest.fixture(autouse=True)
def fresh_plugin_manager(monkeypatch):
    """Each test discovers plugins anew (tests add and break plugins)."""
    import dotshell.plugins

    monkeypatch.setattr(dotshell.plugins, "_default", None)


def make_dist(tmp: Path, dist: str, module: str, source: str, ep_name: str) -> Path:
    """Install a tiny distribution by hand (a dist-info with one dotshell entry point)."""
    info = tmp / f"{dist.replace('-', '_')}-1.0.dist-info"  # PEP 427 escaping
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(f"[dotshell]\n{ep_name} = {module}\n")
    (tmp / f"{module}.py").write_text(source)
    return tmp


@pytest.fixture
def broken_plugin(tmp_path, monkeypatch):
    """A plugin whose import fails, installed on sys.path for this test."""
    path = make_dist(tmp_path / "site", "dotshell-broken", "dotshell_broken_mod",
                     "raise ImportError('needs libfoo.so, which is not installed')\n", "broken")
    monkeypatch.syspath_prepend(str(path))
    return path


def small_profile_dict(factor: float = 0.25, views: int = 6) -> dict:
    """The metal-cylinder profile at reduced resolution (fast tests)."""
    import tomllib

    from dotshell_sim.bench import scale_profile

    raw = tomllib.loads((ROOT / "profiles" / "sim-metal-cylinder.toml").read_text())
    raw = scale_profile(raw, factor)
    raw["scan"]["views"] = views
    return raw


def write_profile(path: Path, raw: dict) -> Path:
    import tomli_w

    path.write_text(tomli_w.dumps(raw))
    return path


def write_test_profile(tmp_path: Path, views: int = 2, name: str = "p.toml",
                       settle_ms: float = 0.0, **outputs) -> Path:
    """The tiny sim bench for front-end tests: 0.12 scale, 1 ray per pixel, previews off
    unless asked."""
    raw = small_profile_dict(factor=0.12, views=views)
    raw["camera"]["settings"]["supersample"] = 1
    raw["scan"]["settle_ms"] = settle_ms
    raw["scan"]["acquisition"] = "show-capture"  # front ends pause and stop between frames
    raw["outputs"] = {"previews": False, **outputs}
    return write_profile(tmp_path / name, raw)


@pytest.fixture
def pm(dotshell_pm):
    """All installed plugins (the dotshell pytest plugin's ``dotshell_pm``)."""
    return dotshell_pm


@pytest.fixture(scope="session")
def small_scan(tmp_path_factory):
    """One reduced-resolution 6-view scan of the metal cylinder, shared by read-only tests."""
    from dotshell.events import EventBus
    from dotshell.pipeline.scan import scan
    from dotshell.plugins import PluginManager
    from dotshell.profile import load_profile

    tmp = tmp_path_factory.mktemp("scan")
    prof_path = write_profile(tmp / "small.toml", small_profile_dict())
    pm = PluginManager()
    pm.load_entry_points()
    events = []
    bus = EventBus()
    bus.subscribe(events.append)
    result = scan(load_profile(prof_path, pm), pm, tmp / "runs", bus=bus)
    return result, events


#: The test files that take longest on one worker (most first; measured with
#: ``pytest -n 2 --dist loadfile --junitxml``, summed by file). They are handed out first, so the
#: two workers of ``make test`` finish together instead of one running a long file alone at the
#: end (xdist's default order, most tests first, put these few-test files last).
LONGEST_FIRST = ("test_tui.py", "test_normalize.py", "test_tui_pty.py", "test_codings_backends.py",
                 "test_hardware_scans.py", "test_device_runs.py", "test_codings_robust.py",
                 "test_calib_sim.py", "test_faults.py", "test_lifecycle.py", "test_mesh.py",
                 "test_serial_faults.py", "test_batch.py", "test_pdi.py", "test_conformance.py")


def pytest_collection_modifyitems(config, items):
    """Full-resolution (slow) checks may run for many minutes: no per-test timeout there.
    Files in :data:`LONGEST_FIRST` order come first (each file's tests keep their order)."""
    for item in items:
        if item.get_closest_marker("slow") is not None:
            item.add_marker(pytest.mark.timeout(0))
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


def pytest_collection_finish(session):
    """The cyclic garbage collector, tuned for a test process: everything imported and
    collected by now (pytest, numpy, numba, Textual, every test module: ~120 k objects) lives
    to the end, so it is frozen out of the collector's passes (``gc.freeze``), and young
    collections run every 7000 allocations instead of 700, so fewer short-lived objects (the
    TUI tests make many: Textual's strips, styles, messages) survive into the old generation
    and set off full passes. Every object is still collected as before, only in fewer passes:
    measured on tests/test_tui.py alone, 29.5-31.4 s of CPU before, 22.9-24.2 s after (two
    interleaved runs each, load 6 on 2 cores); gc.freeze alone gave 26.5-26.7 s."""
    import gc

    gc.collect()
    gc.freeze()
    gc.set_threshold(7000, 10, 10)


# ---- numba kernels compiled once, before the xdist workers run tests ---------------------------

def _is_xdist_controller(config) -> bool:
    return not hasattr(config, "workerinput") and bool(getattr(config.option, "numprocesses", 0))


def _byte_compile_sources() -> None:
    """Write the .pyc files of dotshell and its plugins (only those out of date). Where
    PYTHONDONTWRITEBYTECODE is set, Python never writes them itself, and every `dotshell`
    process, Dask worker and server a test starts compiled ~90 modules from source again
    (0.3-0.7 s of CPU each). A stale .pyc is never used: Python checks the source's mtime."""
    import compileall

    for package in (ROOT / "dotshell", *sorted((ROOT / "plugins").glob("dotshell_*"))):
        compileall.compile_dir(package, quiet=2)


def _rewrite_asserts_of_test_helpers_only(config) -> None:
    """pytest rewrites the asserts of every module of a distribution that has a pytest plugin
    (dotshell: its ``dotshell.testing``; hypothesis) and, where PYTHONDONTWRITEBYTECODE is set,
    cannot keep what it rewrote: each pytest process rewrote from source every dotshell module
    it imported (1.1 s of CPU for all 116) and hypothesis's (~1.5 s, at collection and again in
    the controller's terminal summary). Only dotshell.testing asserts for tests; the others
    load their .pyc files. (A private pytest attribute: where it is missing, nothing changes.)"""
    marked = getattr(getattr(config.pluginmanager, "rewrite_hook", None), "_must_rewrite", None)
    if isinstance(marked, set) and "dotshell" in marked:
        marked.difference_update({"dotshell", "hypothesis"})
        marked.add("dotshell.testing")


def pytest_configure(config):
    """In a process that runs tests: configure it as the ``dotshell`` command configures its
    own (:func:`dotshell.runtime.configure_process`: BLAS on one thread), so the pipeline the
    tests call in-process runs as a lab runs it, whichever test calls ``main()`` first (with
    OpenBLAS's threads, a reduced sim scan took 11.3 s of CPU against 6.7 s).

    In the xdist controller (or a run without workers): byte-compile the sources for the
    processes the tests start. In the xdist controller also: hand the files out in collection
    order, and compile the numba kernels into their on-disk cache in a subprocess
    (tests/compile_kernels.py: its groups in forked children at once) while the workers start
    and collect; the first worker to finish collecting waits for them
    (:func:`pytest_xdist_node_collection_finished`).

    In every process: plugin packages' asserts are not rewritten
    (:func:`_rewrite_asserts_of_test_helpers_only`)."""
    _rewrite_asserts_of_test_helpers_only(config)
    if not hasattr(config, "workerinput"):
        _byte_compile_sources()
    if not _is_xdist_controller(config):
        from dotshell.runtime import configure_process

        configure_process()
    else:
        config.option.loadscopereorder = False  # keep the LONGEST_FIRST order (--dist loadfile)
        config._dotshell_compile = subprocess.Popen(
            [sys.executable, str(ROOT / "tests" / "compile_kernels.py")],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT)


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_node_collection_finished(node, ids):
    """No test is handed out before the kernels are in the cache (else each worker compiles
    them again, ~35 s each)."""
    proc = getattr(node.config, "_dotshell_compile", None)
    if proc is None:
        return
    node.config._dotshell_compile = None
    out, _ = proc.communicate()
    if proc.returncode != 0:  # the tests that decode will fail and say why; say it here too
        node.config.get_terminal_writer().line(
            f"tests/compile_kernels.py failed (exit {proc.returncode}):\n{out}", red=True)
