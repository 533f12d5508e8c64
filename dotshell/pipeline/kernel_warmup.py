"""A scan's compiled kernels made before the scan needs them, in a process of their own.

dotshell's decode, triangulation and FEM kernels are numba functions compiled for the argument
types of their first call and kept in numba's on-disk cache (:mod:`dotshell.runtime.numba_cache`).
The first scan after an install compiled them in the scan process: LLVM's working memory and
what it keeps afterwards stayed in that process beside the capture (the agar scan of 3 views
peaked at 1105 MiB on an empty cache, 930 MiB on a full one; issue 33).

Now a scan asks, once its devices are connected and its frame format known, whether numba's
cache holds every kernel its views will call (:func:`cache_holds`, a few index files read), and
if not, compiles them in a new Python process (:func:`compile_for_run`, through
:func:`dotshell.runtime.child.run_in_child`) while the first view is captured. The
first view's reconstruction waits for that process on its worker thread, the capture going on,
and so does a trans-illumination view (the simulated laser's FEM truth). The child calls the kernels the way a view
does: :func:`~dotshell.pipeline.reconstruct.reconstruct_view` of a synthetic view (the run's
coding, calibration, processing settings and frame depth; a plane through the turntable axis
lit by the coding's patterns, :func:`synthetic_view`), and each of the profile's backends'
:attr:`~dotshell.backends.Backend.compile_kernels` (the simulator's laser: its FEM truth). It
then records which kernels and argument types it needed in a stamp file beside numba's cache
(``dotshell-kernels-KEY.pkl``, KEY from what decides the types: the coding and its settings,
the frame depth, those backends), so the next scan of the same kind checks the cache without a
process. The check uses numba's own index test (the source and the machine's CPU included): a
changed kernel, another CPU or a deleted cache is a miss.

A failure here never stops a scan: its kernels are then compiled where they are first called,
as before, and the scan says why in a warning.

``dotshell reconstruct`` (and any processing that reconstructs views from a run's frames:
:func:`kernels_before_views`, called by :func:`dotshell.pipeline.steps.views_step`) makes the
same check before its first view and, on a miss, says so and waits for the same compiling
process: on an empty cache it showed nothing for ~20 s after "→ reconstruct" (the demo run:
24 s in all, 586 MiB; now 28 s, the process 465 MiB and the compiling one 559 MiB,
2026-12-06).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import pickle
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from dotshell.backends import ROLES
from dotshell.events import EventBus

if TYPE_CHECKING:
    from dotshell.pipeline.steps import StepContext

log = logging.getLogger(__name__)

#: the stamp files' name: ``dotshell-kernels-KEY.pkl`` beside numba's cache of the view kernels
STAMP_PREFIX = "dotshell-kernels-"

#: (module, attribute, numba signature) of one compiled kernel a scan calls
Kernel = tuple[str, str, Any]


@dataclass
class WarmupOutcome:
    """What the child did: the kernel signatures it compiled (not found in numba's cache) and
    its time (seconds)."""

    compiled: int
    seconds: float


def warmup_key(profile_data: dict[str, Any], bit_depth: int, pm: Any) -> str:
    """What decides which kernels a scan calls and their argument types, hashed: the coding
    and its settings, the frame depth (bits), trans-illumination (the FEM's kernels), the
    profile's backends that compile kernels of their own, and the versions of Python and
    numba (16 hex digits)."""
    import numba

    coding = profile_data.get("coding") or {}
    basis = {"coding": coding.get("backend"), "settings": coding.get("settings") or {},
             "bit_depth": int(bit_depth), "numba": numba.__version__,
             "python": sys.version_info[:2], "fem": _needs_fem(profile_data),
             "backends": sorted(f"{f.__module__}.{f.__qualname__}"
                                for f in _backend_compilers(profile_data, pm))}
    text = json.dumps(basis, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def stamp_path(key: str) -> Path:
    """Where the stamp of ``key`` lives: beside numba's cache of the view kernels (so a cache
    deleted or moved with ``NUMBA_CACHE_DIR`` takes its stamps with it)."""
    from dotshell.pipeline import reconstruct

    cache = getattr(reconstruct._keep_points, "_cache")  # noqa: B009 (numba's, undeclared)
    return Path(cache.cache_path) / f"{STAMP_PREFIX}{key}.pkl"


def cache_holds(key: str) -> bool:
    """Whether numba's cache holds every kernel the stamp of ``key`` lists (False without a
    stamp, or on any doubt)."""
    try:
        kernels: list[Kernel] = pickle.loads(stamp_path(key).read_bytes())
        return bool(kernels) and all(_cached(*k) for k in kernels)
    except Exception as exc:  # noqa: BLE001 - a stamp that cannot be read is a miss
        log.debug("kernel stamp %s not usable: %s", key, exc)
        return False


def _cached(module: str, attr: str, sig: Any) -> bool:
    """Whether numba's cache index of ``module.attr`` has ``sig`` for this machine (numba's
    own test: source stamp, CPU, bytecode)."""
    import importlib

    disp = getattr(importlib.import_module(module), attr)
    cache = disp._cache
    key = cache._index_key(sig, disp.targetctx.codegen())
    return key in cache._cache_file._load_index()


def compiled_kernels() -> list[Kernel]:
    """Every kernel with an on-disk cache this process has called, with each argument-type
    signature it was called with."""
    from numba.core.caching import FunctionCache
    from numba.core.registry import CPUDispatcher

    found: list[Kernel] = []
    for name, module in list(sys.modules.items()):
        for attr, value in list(getattr(module, "__dict__", {}).items()):
            # type(), not isinstance(): some modules hold objects whose __class__ raises
            if issubclass(type(value), CPUDispatcher) and value.__module__ == name \
                    and isinstance(getattr(value, "_cache", None), FunctionCache):
                found.extend((name, attr, sig) for sig in value.signatures)
    return found


def synthetic_view(calib: Any, patterns: list[np.ndarray], bit_depth: int,
                   seed: int = 0) -> list[np.ndarray]:
    """The coding's ``patterns`` (uint8 projector images) as the camera of ``calib`` would
    see them on a plane through the turntable axis facing the camera (the image's left half),
    and turned a quarter (the right half: projector columns down the camera's rows): one frame
    per pattern at the camera's size, in the dtype of ``bit_depth``-bit frames (uint8 up to 8
    bits, else uint16), with a dark level and a little noise. Not a rendering: a view whose
    pixels decode and triangulate, with stripes across both image directions, so that a
    view's every kernel is called (the sub-pixel refinement's second pass runs where the
    first leaves many pixels; :meth:`GrayCode._refine_axis`)."""
    cam, proj = calib.camera, calib.projector
    h, w = cam.height, cam.width
    pw, ph = proj.size
    ys, xs = np.mgrid[0:h, 0:w]
    rays = cam.rays(np.column_stack([xs.ravel(), ys.ravel()]).astype(np.float64))
    normal = -calib.axis_point / np.linalg.norm(calib.axis_point)
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = (normal @ calib.axis_point) / (rays @ normal)
        uv = proj.project((rays * depth[:, None]) @ calib.R.T + calib.T)
    uv = np.nan_to_num(np.rint(uv), nan=-1.0, posinf=-1.0, neginf=-1.0).astype(np.int64)
    turned = (xs >= w // 2).ravel()
    uv[turned, 0] = ys.ravel()[turned] * pw // h
    uv[turned, 1] = xs.ravel()[turned] * ph // w
    seen = (turned | (np.isfinite(depth) & (depth > 0))) & (uv[:, 0] >= 0) & (uv[:, 0] < pw) \
        & (uv[:, 1] >= 0) & (uv[:, 1] < ph)
    where = np.where(seen, uv[:, 1] * pw + uv[:, 0], 0)
    full = (1 << bit_depth) - 1
    dtype = np.uint8 if bit_depth <= 8 else np.uint16
    rng = np.random.default_rng(seed)
    frames = []
    for pattern in patterns:
        lit = np.where(seen, pattern.ravel()[where], 0).astype(np.float32) / 255.0
        signal = full * (0.05 + 0.8 * lit) + rng.normal(0.0, 0.005 * full, lit.shape)
        frames.append(np.clip(signal, 0, full).astype(dtype).reshape(h, w))
    return frames


def compile_for_run(run_root: str, bit_depth: int) -> WarmupOutcome:
    """In this process: call every kernel a view of the run at ``run_root`` calls (its
    profile, calibration and ``bit_depth``-bit frames) and its backends' own
    (:attr:`~dotshell.backends.Backend.compile_kernels`), so numba's cache holds them all; then
    write the stamp of the run's kind. Returns what it compiled."""
    from dotshell.geometry.calibration import RigCalibration
    from dotshell.pipeline.reconstruct import reconstruct_view
    from dotshell.pipeline.steps import make_coding
    from dotshell.plugins import get_plugin_manager
    from dotshell.profile.loader import validate_profile
    from dotshell.run.layout import RunLayout
    from dotshell.run.store import RunStore

    t0 = time.perf_counter()
    pm = get_plugin_manager()
    store = RunStore(Path(run_root))
    profile = validate_profile(store.read_profile(), pm, str(store.path(RunLayout.PROFILE)),
                               store.root)
    calib = RigCalibration.load(store.path(RunLayout.CALIBRATION))
    coding = make_coding(profile, pm)
    patterns = [p.image for p in coding.patterns(calib.projector.size)]
    frames = synthetic_view(calib, patterns, bit_depth)
    reconstruct_view(0, 0.0, frames, coding, calib, profile.processing)
    if _needs_fem(profile.data):
        compile_fem_kernels()
    for compile_backend in _backend_compilers(profile.data, pm):
        compile_backend()
    kernels = compiled_kernels()
    _write_stamp(warmup_key(profile.data, bit_depth, pm), kernels)
    misses = sum(_misses(module, attr) for module, attr in {(m, a) for m, a, _ in kernels})
    return WarmupOutcome(misses, time.perf_counter() - t0)


def _needs_fem(profile_data: dict[str, Any]) -> bool:
    """Whether a scan of the profile may call the FEM's kernels in its process: with
    trans-illumination, the normalization may run after the scan."""
    return bool((profile_data.get("transillumination") or {}).get("enabled"))


def compile_fem_kernels() -> None:
    """Call the FEM's and the surface queries' kernels (the normalization's, after a scan with
    trans-illumination) on a cube of five tetrahedra: its boundary, the system matrix's
    pattern and assembly, a forward solve, the element holding a point, and ray casts and
    closest points on its boundary."""
    from dotshell.fem.forward import solve_cw
    from dotshell.fem.meshes import TetMesh, orient_positive
    from dotshell.geometry.bvh import TriangleBVH

    corners = 10.0 * np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], float)
    tets = np.array([[0, 1, 2, 4], [1, 3, 2, 7], [1, 2, 4, 7], [1, 5, 4, 7], [2, 4, 7, 6]])
    mesh = TetMesh(corners, orient_positive(corners, tets))
    solve_cw(mesh, [5.0, 5.0, 5.0], np.full(8, 0.01), np.full(8, 1.0), 1.37)
    surface = TriangleBVH(mesh.nodes, mesh.boundary_faces)
    inside = np.full((4, 3), 5.0)
    surface.cast(np.zeros_like(inside), inside)
    surface.closest(inside)


def _backend_compilers(profile_data: dict[str, Any], pm: Any) -> list[Callable[[], None]]:
    """The ``compile_kernels`` of the profile's backends that have one."""
    out = []
    for role in ROLES:
        section = profile_data.get(role)
        if not section or role == "coding":
            continue
        backend = pm.backend(role, section["backend"]).backend
        if backend.compile_kernels is not None:
            out.append(backend.compile_kernels)
    return out


def _misses(module: str, attr: str) -> int:
    """Signatures of ``module.attr`` this process compiled (not found in numba's cache)."""
    disp = getattr(sys.modules[module], attr)
    return sum(disp.stats.cache_misses.values())


def _write_stamp(key: str, kernels: list[Kernel]) -> None:
    """Write the stamp of ``key`` atomically; a cache directory that cannot be written (a
    read-only install: numba then caches elsewhere or not at all) leaves no stamp."""
    path = stamp_path(key)
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_bytes(pickle.dumps(kernels))
        os.replace(tmp, path)
    except OSError as exc:
        log.debug("kernel stamp not written to %s: %s", path, exc)
        tmp.unlink(missing_ok=True)


#: the kinds of scan (:func:`warmup_key`) whose failure to compile ahead was told
_WARNED: set[str] = set()


class KernelWarmup:
    """The scan's side: from :meth:`start` on, a thread checks numba's cache for the run's
    kernels and, on a miss, compiles them in a child process; :meth:`wait` joins it before
    the scan's first kernel call and tells the user what was done or went wrong."""

    def __init__(self, run_root: Path, profile_data: dict[str, Any], bit_depth: int,
                 pm: Any, announce: EventBus | None = None) -> None:
        self._args = (str(run_root), profile_data, int(bit_depth), pm)
        self._announce = announce
        self._said: tuple[str, str] | None = None  # (level, text) for the user
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="dotshell-kernels", daemon=True)

    @classmethod
    def start(cls, run_root: Path, profile_data: dict[str, Any], bit_depth: int, pm: Any,
              announce: EventBus | None = None) -> KernelWarmup:
        """Check the cache and compile what it lacks, on a thread, from now on; ``announce``:
        a bus told when the compiling starts (for a caller that waits at once, with nothing
        else to show: ``reconstruct``)."""
        warmup = cls(run_root, profile_data, bit_depth, pm, announce)
        warmup._thread.start()
        return warmup

    def _run(self) -> None:
        from dotshell.runtime.child import run_in_child

        run_root, profile_data, bit_depth, pm = self._args
        key = ""
        try:
            key = warmup_key(profile_data, bit_depth, pm)
            if cache_holds(key):
                return
            if self._announce is not None:
                self._announce.info("compiling dotshell's kernels for this machine first, in a "
                                    "process of their own (once: numba's cache keeps them; "
                                    "~20-60 s)")
            done: WarmupOutcome = run_in_child(compile_for_run, run_root, bit_depth,
                                                job="kernel compiling")
            if done.compiled:
                text = (f"compiled {done.compiled} of dotshell's kernels for this machine in "
                        f"{done.seconds:.0f} s (once: numba's cache keeps them)")
                self._said = ("info", text)
        except Exception as exc:  # noqa: BLE001 - the scan compiles them itself instead
            text = (f"dotshell's kernels could not be compiled beforehand ({exc}); the scan "
                    "compiles them where it first needs them, with more memory in the scan "
                    "process")
            if key not in _WARNED:  # once a process for a kind (a console's scans)
                _WARNED.add(key)
                self._said = ("warning", text)
            else:
                log.info("%s", text)

    def wait(self, bus: EventBus, stop: threading.Event | None = None) -> None:
        """Block until the kernels are ready (or ``stop`` is set: the scan then compiles
        what it needs itself); the first call after they are tells ``bus`` what was done or
        went wrong. Any thread may call it, any number of times."""
        while self._thread.is_alive() and not (stop is not None and stop.is_set()):
            self._thread.join(0.2)  # a stop is seen within 0.2 s
        if self._thread.is_alive():  # stopped waiting: the outcome is told by a later call
            return
        with self._lock:
            said, self._said = self._said, None
        if said is not None:
            level, text = said
            (bus.warn if level == "warning" else bus.info)(text)


def kernels_before_views(ctx: StepContext, view: int) -> None:
    """Before the first view a processing job reconstructs from the run's frames
    (:class:`~dotshell.pipeline.steps.StepContext` ``ctx``, view ``view``): numba's cache
    checked for the run's kind, and on a miss its kernels compiled in a process of their own,
    the user told before and after."""
    from dotshell.pipeline.steps import stored_frame_spec

    bit_depth = stored_frame_spec(ctx.store, view, ctx.calibration).bit_depth
    KernelWarmup.start(ctx.store.run_root, ctx.profile.data, bit_depth, ctx.pm,
                       announce=ctx.bus).wait(ctx.bus)
