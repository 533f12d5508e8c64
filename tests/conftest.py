import contextlib
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


def _runtime_dir_of_this_test_session() -> None:
    """Device locks and server sockets live in the user's runtime directory, one for every
    dotshell process of the user: the lock of a device says who drives it. Two test sessions at
    once on one machine (a developer's and CI's, or several worktrees) would see each other's
    emulated devices there: a pseudo-terminal an emulator closes (an unplug test) can be handed
    to the other session's emulator under the same /dev/pts number while the first session's
    scan still holds its lock, and that scan's lock then refuses the other (DeviceInUse). So
    each test session, with its xdist workers and the subprocesses they start, gets a runtime
    directory of its own (tests that need another set XDG_RUNTIME_DIR themselves)."""
    import atexit
    import shutil
    import tempfile

    if os.environ.get("DOTSHELL_TEST_RUNTIME_DIR"):
        return  # an xdist worker, or a process a test started: the session's directory
    d = tempfile.mkdtemp(prefix="dotshell-tests-runtime-")  # mode 0700
    os.environ["XDG_RUNTIME_DIR"] = os.environ["DOTSHELL_TEST_RUNTIME_DIR"] = d
    atexit.register(shutil.rmtree, d, True)


_runtime_dir_of_this_test_session()


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
    from dotshell.profile.loader import load_profile

    tmp = tmp_path_factory.mktemp("scan")
    prof_path = write_profile(tmp / "small.toml", small_profile_dict())
    pm = PluginManager()
    pm.load_entry_points()
    events = []
    bus = EventBus()
    bus.subscribe(events.append)
    result = scan(load_profile(prof_path, pm), pm, tmp / "runs", bus=bus)
    return result, events


#: The test files that call no numba kernel, in their process or any process they start (measured:
#: each file run alone with numba's ``Dispatcher._compile_for_args`` logged, in subprocesses too),
#: longest first. In ``make test`` they are handed out first: they run while the controller
#: compiles the kernels (:class:`KernelCompile`), filling the cores their waits on devices and
#: terminals leave idle. A file that calls kernels and is listed here only costs time: its
#: worker compiles what it calls.
KERNEL_FREE = ("test_wheel.py",  # ~50 s; its kernels compile in the installed wheel's processes
               "test_serial_faults.py", "test_tui_snapshots.py", "test_conformance.py",
               "test_projectors.py", "test_mesh_phantoms.py", "test_device_handles.py",
               "test_calib_solve.py", "test_device_plugin_guide.py", "test_compat.py",
               "test_numba_cache.py",
               "test_sim.py", "test_plugins.py", "test_ports_cli.py", "test_settings.py",
               "test_docs.py", "test_store.py", "test_cameras.py", "test_hugepages.py",
               "test_parallel.py", "test_validate_full.py", "test_layers.py",
               "test_profile_sections.py")

#: The other test files that take longest on one worker, most first (measured with
#: ``pytest -n 2 --dist loadfile --junitxml``, summed by file; with a clean clone's compiles in
#: the tests: test_codings_backends compiles the float32 decoder, test_geometry the rays path,
#: kernels no group compiles). They follow :data:`KERNEL_FREE`, so the two workers of
#: ``make test`` finish together instead of one running a long file alone at the end (xdist's
#: default order, most tests first, put these few-test files last).
LONGEST_FIRST = ("test_tui.py", "test_normalize.py", "test_tui_pty.py", "test_hardware_scans.py",
                 "test_faults.py", "test_device_runs.py", "test_codings_backends.py",
                 "test_calib_sim.py", "test_lifecycle.py", "test_mesh.py", "test_batch.py",
                 "test_pdi.py", "test_cli.py", "test_readers.py", "test_calib_captures.py",
                 "test_graycode.py", "test_server.py", "test_fem.py", "test_sequenced.py",
                 "test_sim_transillum.py", "test_runner.py", "test_baselines.py",
                 "test_geometry.py", "test_decode_reference.py", "test_frames.py",
                 "test_console.py")


def pytest_collection_modifyitems(config, items):
    """Full-resolution (slow) checks may run for many minutes: no per-test timeout there.
    Files in :data:`KERNEL_FREE` then :data:`LONGEST_FIRST` order come first (each file's tests
    keep their order)."""
    for item in items:
        if item.get_closest_marker("slow") is not None:
            item.add_marker(pytest.mark.timeout(0))
    rank = {name: i for i, name in enumerate(KERNEL_FREE + LONGEST_FIRST)}
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


# ---- numba kernels compiled once, while the xdist workers run the tests that need none ------

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
    own (:func:`dotshell.runtime.process.configure_process`: BLAS on one thread), so the pipeline the
    tests call in-process runs as a lab runs it, whichever test calls ``main()`` first (with
    OpenBLAS's threads, a reduced sim scan took 11.3 s of CPU against 6.7 s).

    In the xdist controller (or a run without workers): byte-compile the sources for the
    processes the tests start. In the xdist controller also: hand the files out in collection
    order, and compile the numba kernels into their on-disk cache in the background
    (:class:`KernelCompile`) while the workers start, collect and run the files that call no
    kernel (:data:`KERNEL_FREE`); a test of any other file waits for the kernels
    (:func:`pytest_runtest_setup`).

    In every process: plugin packages' asserts are not rewritten
    (:func:`_rewrite_asserts_of_test_helpers_only`)."""
    _rewrite_asserts_of_test_helpers_only(config)
    if not hasattr(config, "workerinput"):
        _byte_compile_sources()
    if not _is_xdist_controller(config):
        from dotshell.runtime.process import configure_process

        configure_process()
    else:
        config.option.loadscopereorder = False  # keep the order of pytest_collection_modifyitems
        config._dotshell_kernels = KernelCompile()


class KernelCompile:
    """tests/compile_kernels.py (its groups in forked children at once) in the background of
    the xdist controller; :attr:`ready` (a file) appears when it has ended, whether it
    succeeded or not (its output is then in :attr:`failure`, if it failed)."""

    def __init__(self) -> None:
        import tempfile
        import threading

        self._dir = tempfile.TemporaryDirectory(prefix="dotshell-kernels-")
        self.ready = Path(self._dir.name) / "ready"
        self.failure: str | None = None
        self._proc = subprocess.Popen(
            [sys.executable, str(ROOT / "tests" / "compile_kernels.py")],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT,
            start_new_session=True)  # its own process group: stopped with its forked children
        self._waiter = threading.Thread(target=self._wait, daemon=True)
        self._waiter.start()

    def _wait(self) -> None:
        try:
            out, _ = self._proc.communicate()
            code = self._proc.returncode
            if code != 0:
                self.failure = f"tests/compile_kernels.py failed (exit {code}):\n{out}"
        finally:
            self.ready.touch()

    def stop(self) -> None:
        """Stop it if it still runs (a run of a few kernel-free tests ended first), and remove
        :attr:`ready`'s directory."""
        if self._proc.poll() is None:
            import signal

            with contextlib.suppress(ProcessLookupError):
                os.killpg(self._proc.pid, signal.SIGTERM)
        self._waiter.join()
        self._dir.cleanup()


@pytest.hookimpl(optionalhook=True)
def pytest_configure_node(node):
    """Each xdist worker is told where :attr:`KernelCompile.ready` appears."""
    kernels = getattr(node.config, "_dotshell_kernels", None)
    if kernels is not None:
        node.workerinput["dotshell_kernels_ready"] = str(kernels.ready)


#: how long a worker waits for the kernels at most (then its tests compile what they need)
KERNELS_WAIT_S = 600.0

_kernels_ready = False


def pytest_runtest_setup(item):
    """In an xdist worker, a test of a file that calls kernels waits until the controller's
    :class:`KernelCompile` has ended (else the worker compiles them too, ~20-40 s of CPU,
    while the other does the same)."""
    global _kernels_ready
    ready = getattr(item.config, "workerinput", {}).get("dotshell_kernels_ready")
    if _kernels_ready or ready is None or item.path.name in KERNEL_FREE:
        return
    deadline = time.monotonic() + KERNELS_WAIT_S
    while not os.path.exists(ready) and time.monotonic() < deadline:
        time.sleep(0.05)
    _kernels_ready = True


def pytest_terminal_summary(terminalreporter, config):
    """The kernels' compile, if it failed (the tests that decode fail too and say why), and
    this host's speed: the suite's time means little without it (the same tree's ``make test``
    took from ~3 to ~4.5 minutes on this project's 2-core host as its speed varied, day to day,
    by up to 2x; docs/performance.md, "Test suite time")."""
    kernels = getattr(config, "_dotshell_kernels", None)
    if kernels is not None and kernels.failure:
        terminalreporter.write_line(kernels.failure, red=True)
    terminalreporter.write_line(f"host speed: 2·10⁷ Python additions in {_additions_s():.2f} s "
                                "(docs/performance.md's yardstick; 1.75 s on its fastest day)")


def _additions_s() -> float:
    """Seconds this process takes for 2·10⁷ pure-Python additions at a module's top level (as
    the yardstick was run: ``python3 -c "s=0\nfor i in range(20000000): s+=i"``), timed on a
    tenth of them."""
    t0 = time.perf_counter()
    exec("s = 0\nfor i in range(2_000_000):\n    s += i\n", {})
    return 10 * (time.perf_counter() - t0)


def pytest_unconfigure(config):
    kernels = getattr(config, "_dotshell_kernels", None)
    if kernels is not None:
        kernels.stop()
