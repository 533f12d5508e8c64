"""pytest helpers for plugin authors, registered as a pytest11 plugin (available in any test
suite once dotshell is installed): the device conformance kit and a serial-emulator fixture.

Fixtures:
    dotshell_pm: a fresh :class:`~dotshell.plugins.PluginManager` with all installed entry
        points loaded (load errors in ``dotshell_pm.load_errors``).
    serial_emulator: ``serial_emulator("grbl", **options)`` starts that emulator (from the
        ``dotshell_emulators`` entry-point group) on a real pseudo-terminal behind a stable link
        in the test's temporary directory and stops it after the test; ``emu.port`` is what the
        driver's ``port`` setting names.

Functions:
    assert_device_conforms(pm, role, name, settings, ...): the behavioural checks of
        :func:`check_device` (one line in a driver's test suite); fails naming every broken rule.
    assert_backend_conforms(pm, role, name, settings=None): the same for device roles; codings
        and exporters get their interface checked.

Rules (names appear in failures; docs/devices.md explains each):
    ``protocol-members``, ``properties-hardware-free``, ``status-cheap``, ``connect-close-twice``,
    ``call-before-connect``, ``failed-connect``, ``close-after-failed-connect``,
    ``raises-device-errors``, ``capture-shape``, ``capture-dtype``, ``capture-bit-depth``,
    ``show-pattern``, ``show-rejects-bad-pattern``, ``move-reaches-angle``, ``rejects-bad-angle``,
    ``set-angle``, ``set-on-off``, ``stop-when-idle``, ``stop-returns-fast``,
    ``stop-interrupts-move``, ``home``, ``read-angle``, ``identity``, ``frame-info``,
    ``set-exposure``; kit v2: ``returns-in-time`` (every step within ``call_limit_s``; a step
    that hangs fails it and the rules after it are listed as skipped), ``capture-not-none``,
    ``frame-info-advances`` (two frames' timestamps and ids rise: no stale frame),
    ``stop-during-home``, and with the author's ``faults`` hooks ``lost-device`` and
    ``deadline-respected``.

:func:`format_results` lists every rule run (ok, FAIL, skip); :func:`assert_device_conforms`
prints it, so ``pytest -rA`` shows what was checked.
"""

from __future__ import annotations

import json
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import pytest

from dotshell import devices as dv
from dotshell.backends import RigContext
from dotshell.coding import PatternCoding
from dotshell.errors import DeviceError, DotshellError
from dotshell.plugins import PluginManager

#: How long ``status()`` may take (seconds): front ends poll it about once a second.
STATUS_BUDGET_S = 0.5
#: How long ``stop()`` itself may take (seconds).
STOP_RETURN_S = 0.2


@dataclass(frozen=True)
class RuleResult:
    """One conformance rule checked on one backend."""

    rule: str
    passed: bool
    detail: str = ""
    skipped: bool = False

    def __str__(self) -> str:
        mark = "skip" if self.skipped else "ok  " if self.passed else "FAIL"
        return f"{mark} {self.rule}" + (f": {self.detail}" if self.detail else "")


def format_results(results: list[RuleResult], label: str = "") -> str:
    """The rules run on one backend, one per line (``ok``, ``FAIL`` or ``skip``)."""
    head = f"{label}: " if label else ""
    passed = sum(r.passed and not r.skipped for r in results)
    lines = [f"{head}{passed} of {len(results)} rules passed"]
    return "\n".join(lines + [f"  {r}" for r in results])


#: How long one step of the kit may take by default (seconds).
CALL_LIMIT_S = 30.0


class _Hung(Exception):
    """A step did not return within the call limit (the device is left alone after it)."""


class _Checker:
    def __init__(self, label: str, limit_s: float = CALL_LIMIT_S) -> None:
        self.label = label
        self.limit_s = limit_s
        self.hung: str | None = None  # the step that did not return
        self.results: list[RuleResult] = []

    def limited(self, step: str, fn: Callable[[], Any]) -> Any:
        """``fn()`` on a helper thread, waited for at most ``limit_s``; :class:`_Hung` past it
        (the thread is abandoned: a hung driver must not hang the kit)."""
        box: list[tuple[bool, Any]] = []

        def run() -> None:
            try:
                box.append((True, fn()))
            except BaseException as exc:  # re-raised on the caller's thread
                box.append((False, exc))

        worker = threading.Thread(target=run, name="dotshell-kit-call", daemon=True)
        worker.start()
        worker.join(self.limit_s)
        if not box:
            self.hung = step
            raise _Hung(step)
        ok, value = box[0]
        if not ok:
            raise value
        return value

    def rule(self, name: str, step: str, fn: Callable[[], Any], any_error: bool = False) -> Any:
        """Run ``fn`` for rule ``name`` within the call limit; assertion failures fail the
        rule, exceptions other than DotshellError fail ``raises-device-errors`` (``any_error``:
        fail ``name``, for steps that must not raise at all). After a hung step every rule is
        skipped."""
        if self.hung is not None:
            self.results.append(RuleResult(name, False, f"not run: {self.hung} never returned",
                                           skipped=True))
            return None
        try:
            value = self.limited(step, fn)
        except _Hung:
            self.results.append(RuleResult(
                "returns-in-time", False, f"{step} did not return within {self.limit_s:g} s "
                "(the kit's call_limit_s); a driver call must end — by its own timeout "
                "(context.time_left()) if the device does not answer"))
            return None
        except AssertionError as exc:
            self.results.append(RuleResult(name, False, str(exc) or step))
            return None
        except DotshellError as exc:
            self.results.append(RuleResult(name, False, f"{step} raised {type(exc).__name__}: "
                                                        f"{exc}"))
            return None
        except Exception as exc:
            if any_error:
                self.results.append(RuleResult(name, False, f"{step} raised "
                                                            f"{type(exc).__name__}: {exc}"))
                return None
            self.results.append(RuleResult(
                "raises-device-errors", False, f"{step} raised {type(exc).__name__}: {exc}; "
                "drivers must raise dotshell.errors.DeviceError (with a fix) for device "
                "failures"))
            return None
        self.results.append(RuleResult(name, True))
        return value

    def fail(self, name: str, detail: str) -> None:
        self.results.append(RuleResult(name, False, detail))


def _expect_device_error(step: str, fn: Callable[[], Any]) -> None:
    try:
        fn()
    except DeviceError:
        return
    except DotshellError as exc:
        raise AssertionError(f"{step} raised {type(exc).__name__}, not a DeviceError") from None
    raise AssertionError(f"{step} did not raise DeviceError")


def _timed_status(dev: Any, when: str) -> None:
    t0 = time.perf_counter()
    st = dev.status()
    took = time.perf_counter() - t0
    assert isinstance(st, dict), f"status() {when} returned {type(st).__name__}, not a dict"
    try:
        json.dumps(st)
    except (TypeError, ValueError) as exc:
        raise AssertionError(f"status() {when} is not JSON-serialisable ({exc})") from None
    assert took <= STATUS_BUDGET_S, (f"status() {when} took {took:.2f} s (> {STATUS_BUDGET_S} s); "
                                     "it must be cheap: report what the driver knows")


def _properties(role: str) -> list[str]:
    proto = dv.ROLE_PROTOCOLS[role]
    return [n for k in proto.__mro__ for n, v in vars(k).items() if isinstance(v, property)]


def check_device(pm: PluginManager, role: str, name: str, settings: dict[str, Any] | None = None,
                 *, context: RigContext | None = None,
                 failing_settings: dict[str, Any] | None = None, move_deg: float = 180.0,
                 stop_within_s: float = 2.0, angle_tolerance_deg: float = 0.05,
                 call_limit_s: float = CALL_LIMIT_S,
                 prepare: Callable[[Any], Any] | None = None,
                 faults: dict[str, Callable[[], Any]] | None = None,
                 deadline_s: float = 1.0) -> list[RuleResult]:
    """Run the behavioural conformance rules on backend ``name`` of device ``role``.

    Args:
        settings: settings that reach a working device (e.g. an emulator's port).
        context: the rig context to build in (e.g. one whose sim world has the peers a camera
            needs); default a fresh one.
        failing_settings: settings whose ``connect()`` must fail (e.g. a port that does not
            exist), for ``failed-connect`` and ``close-after-failed-connect``.
        move_deg: how far the stop test moves a stage or analyzer (degrees).
        stop_within_s: how long a stopped move may take to return (seconds).
        angle_tolerance_deg: how close ``position`` must come to a commanded angle.
        call_limit_s: how long any one step may take (seconds): a step still running then
            fails ``returns-in-time`` and the rules after it are skipped.
        prepare: called with the connected device before the rules (home it, load a
            configuration, put an emulator in a known state).
        faults: the author's fault switches, each a no-argument callable (plugin-defined
            faults, e.g. an emulator's): ``"lost"`` makes the device vanish (the next call must
            raise DeviceLostError: rule ``lost-device``), ``"stuck"`` makes moves never end (a
            move must give up by its deadline, ``deadline_s`` from the call: rule
            ``deadline-respected``). Run last, after every other rule.
        deadline_s: the deadline ``deadline-respected`` gives the move (seconds).
    """
    ctx = context or RigContext()
    c = _Checker(f"{role} backend {name!r}", call_limit_s)
    dctx = ctx.for_device(role, name)
    dev = pm.create(role, name, settings, dctx, "conformance")
    missing = dv.missing_members(dev, dv.ROLE_PROTOCOLS[role])
    if missing:
        c.fail("protocol-members", f"{type(dev).__name__} lacks {', '.join(missing)} of the "
                                   f"{role} protocol (checked on the class)")
        return c.results
    c.results.append(RuleResult("protocol-members", True))
    c.rule("properties-hardware-free", "reading the properties before connect()",
           lambda: [getattr(dev, p) for p in _properties(role)])
    c.rule("status-cheap", "status() before connect()", lambda: _timed_status(dev, "before "
                                                                                "connect()"))
    main = _main_call(role, dev)
    c.rule("call-before-connect", f"{main[0]} before connect()",
           lambda: _expect_device_error(f"{main[0]} before connect()", main[1]))
    if failing_settings is not None:
        bad = pm.create(role, name, failing_settings, ctx.for_device(role, name), "conformance")
        c.rule("failed-connect", "connect() with failing settings",
               lambda: _expect_device_error("connect() with failing settings", bad.connect))
        c.rule("close-after-failed-connect", "close() after a failed connect()", bad.close,
               any_error=True)
    if not c.rule("connect-close-twice", "connect/close/connect/close/close",
                  lambda: (dev.connect(), dev.close(), dev.connect(), dev.close(), dev.close())
                  ) and c.results[-1].passed is False:
        return c.results
    if c.rule("connect", "connect()", dev.connect) is None and not c.results[-1].passed:
        return _merge(c.results)
    try:
        if prepare is not None:
            c.rule("prepare", "the prepare hook", lambda: prepare(dev), any_error=True)
        c.rule("status-cheap", "status() while connected",
               lambda: _timed_status(dev, "while connected"))
        _check_role(c, role, dev, angle_tolerance_deg)
        _check_capabilities(c, role, dev, move_deg, stop_within_s, angle_tolerance_deg)
        _check_faults(c, role, dev, dctx, faults or {}, deadline_s)
    finally:
        if c.hung is None:
            c.rule("connect-close-twice", "close()", dev.close, any_error=True)
    c.rule("status-cheap", "status() after close()", lambda: _timed_status(dev, "after close()"))
    if dv.implements(dev, dv.Stoppable):
        c.rule("stop-when-idle", "stop() after close()", dev.stop, any_error=True)
    return _merge(c.results)


def _check_faults(c: _Checker, role: str, dev: Any, ctx: RigContext,
                  faults: dict[str, Callable[[], Any]], deadline_s: float) -> None:
    """The failure paths the author can provoke (see :func:`check_device`'s ``faults``)."""
    from dotshell.errors import DeviceLostError

    unknown = set(faults) - {"lost", "stuck"}
    if unknown:
        raise ValueError(f"unknown fault hooks {sorted(unknown)}; the kit knows 'lost' and "
                         "'stuck'")
    main = _main_call(role, dev)
    if "stuck" in faults and role in ("stage", "analyzer"):
        def respected() -> None:
            faults["stuck"]()
            ctx.deadline = time.monotonic() + deadline_s
            t0 = time.monotonic()
            try:
                _expect_device_error(f"{main[0]} on a stuck device", main[1])
            finally:
                ctx.deadline = math.inf
            took = time.monotonic() - t0
            assert took <= deadline_s + 2.0, (
                f"{main[0]} on a stuck device gave up after {took:.1f} s, past its deadline of "
                f"{deadline_s:g} s (+2 s grace); watch context.time_left() while waiting")

        c.rule("deadline-respected", f"{main[0]} on a stuck device", respected)
    if "lost" in faults:
        def lost() -> None:
            faults["lost"]()
            try:
                main[1]()
            except DeviceLostError:
                return
            except DeviceError as exc:
                raise AssertionError(f"{main[0]} on a vanished device raised "
                                     f"{type(exc).__name__} ({exc}), not DeviceLostError: the "
                                     "rig reconnects only a DeviceLostError") from None
            raise AssertionError(f"{main[0]} on a vanished device did not raise")

        c.rule("lost-device", f"{main[0]} after the device vanished", lost)


def _merge(results: list[RuleResult]) -> list[RuleResult]:
    """One result per rule: failed if any check of it failed (first failure's detail)."""
    out: dict[str, RuleResult] = {}
    for r in results:
        if r.rule not in out or (out[r.rule].passed and not r.passed):
            out[r.rule] = r
    return list(out.values())


def _main_call(role: str, dev: Any) -> tuple[str, Callable[[], Any]]:
    if role == "camera":
        return "capture()", dev.capture
    if role == "projector":
        return "show()", lambda: dev.show(np.zeros((8, 8), np.uint8))
    if role == "stage":
        return "move_to(10)", lambda: dev.move_to(10.0)
    if role == "analyzer":
        return "set_angle(10)", lambda: dev.set_angle(10.0)
    return "set(True)", lambda: dev.set(True)


def _check_role(c: _Checker, role: str, dev: Any, tol: float) -> None:
    if role == "camera":
        _check_camera(c, dev)
    elif role == "projector":
        w, h = dev.resolution
        c.rule("show-pattern", f"show(a black {h}x{w} uint8 pattern)",
               lambda: dev.show(np.zeros((h, w), np.uint8)))
        c.rule("show-rejects-bad-pattern", "show(a float (3, 3, 3) array)",
               lambda: _expect_device_error("show(a float (3, 3, 3) array)",
                                            lambda: dev.show(np.zeros((3, 3, 3)))))
    elif role == "stage":
        def reach() -> None:
            dev.move_to(30.0)
            pos = float(dev.position)
            assert abs(pos - 30.0) <= tol, (f"after move_to(30) position is {pos:g}°, not within "
                                            f"{tol:g}° of 30°")

        c.rule("move-reaches-angle", "move_to(30)", reach)
        c.rule("rejects-bad-angle", "move_to(nan)", lambda: _expect_device_error(
            "move_to(nan)", lambda: dev.move_to(math.nan)))
    elif role == "analyzer":
        c.rule("set-angle", "set_angle(90)", lambda: dev.set_angle(90.0))
        c.rule("rejects-bad-angle", "set_angle(nan)", lambda: _expect_device_error(
            "set_angle(nan)", lambda: dev.set_angle(math.nan)))
    else:
        c.rule("set-on-off", "set(True); set(False)", lambda: (dev.set(True), dev.set(False)))


def _check_camera(c: _Checker, dev: Any) -> None:
    frame = c.rule("capture-shape", "capture()", dev.capture)
    if frame is None and not c.results[-1].passed:
        return
    w, h = dev.resolution
    bits = int(dev.bit_depth)
    want = np.uint8 if bits <= 8 else np.uint16

    def not_none() -> None:
        assert frame is not None, ("capture() returned None (no frame); return the frame, or "
                                   "raise DeviceError saying why there is none")

    def shape() -> None:
        assert isinstance(frame, np.ndarray), f"capture() returned {type(frame).__name__}"
        assert frame.shape == (h, w), (f"capture() returned shape {frame.shape}, but resolution "
                                       f"is {w}x{h} → expected ({h}, {w})")

    def dtype() -> None:
        assert isinstance(frame, np.ndarray) and frame.dtype == want, (
            f"capture() returned {getattr(frame, 'dtype', type(frame).__name__)}, but bit_depth "
            f"{bits} needs {np.dtype(want).name}")

    def depth() -> None:
        assert isinstance(frame, np.ndarray) and frame.size and int(frame.max()) < 2 ** bits, (
            f"capture() has values up to {frame.max() if frame.size else 'none'}, above the "
            f"{bits}-bit range 0..{2 ** bits - 1}")

    c.results.pop()  # capture-shape is decided below
    if not c.rule("capture-not-none", "capture()", not_none) and frame is None:
        return
    c.rule("capture-shape", "capture()", shape)
    c.rule("capture-dtype", "capture()", dtype)
    c.rule("capture-bit-depth", "capture()", depth)


def _check_capabilities(c: _Checker, role: str, dev: Any, move_deg: float, stop_within_s: float,
                        tol: float) -> None:
    moves = role in ("stage", "analyzer")
    if dv.implements(dev, dv.Stoppable):
        c.rule("stop-when-idle", "stop() while nothing moves", dev.stop, any_error=True)
        if moves:
            _check_stop(c, role, dev, move_deg, stop_within_s)
    if dv.implements(dev, dv.Homing):
        def home() -> None:
            dev.home()
            pos = getattr(dev, "position", 0.0)
            if role == "stage":
                assert abs(float(pos)) <= tol, f"after home() position is {pos:g}°, not 0°"

        c.rule("home", "home()", home)
    if dv.implements(dev, dv.AngleReadback) and moves:
        def read() -> None:
            (dev.move_to if role == "stage" else dev.set_angle)(45.0)
            got = float(dev.read_angle())
            assert abs(got - 45.0) <= tol, f"read_angle() after moving to 45° is {got:g}°"

        c.rule("read-angle", "read_angle()", read)
    if dv.implements(dev, dv.Identified):
        c.rule("identity", "identity()", lambda: _is(dev.identity(), dv.DeviceIdentity,
                                                     "identity()"))
    if dv.implements(dev, dv.FrameInfoSource) and role == "camera":
        def frame_info() -> None:
            dev.capture()
            _is(dev.last_frame_info(), dv.FrameInfo, "last_frame_info()")

        c.rule("frame-info", "last_frame_info() after capture()", frame_info)
        c.rule("frame-info-advances", "two captures' last_frame_info()",
               lambda: _frame_info_advances(dev))
    if dv.implements(dev, dv.Homing) and dv.implements(dev, dv.Stoppable) and moves:
        _check_stop(c, role, dev, move_deg, stop_within_s, during_home=True)
    if dv.implements(dev, dv.ExposureControl):
        def exposure() -> None:
            dev.set_exposure(10.0)
            _expect_device_error("set_exposure(-1)", lambda: dev.set_exposure(-1.0))

        c.rule("set-exposure", "set_exposure(10); set_exposure(-1)", exposure)


def _is(value: Any, kind: type, what: str) -> None:
    assert isinstance(value, kind), f"{what} returned {type(value).__name__}, not {kind.__name__}"


def _frame_info_advances(dev: Any) -> None:
    """Each frame is new: timestamps rise, and frame ids (when known) rise."""
    dev.capture()
    a = dev.last_frame_info()
    dev.capture()
    b = dev.last_frame_info()
    if math.isfinite(a.timestamp_s) and math.isfinite(b.timestamp_s):
        assert b.timestamp_s > a.timestamp_s, (
            f"two captures report timestamps {a.timestamp_s!r} and {b.timestamp_s!r}: the second "
            "frame is not newer (a stale or repeated frame); report each frame's own time")
    if a.frame_id >= 0 and b.frame_id >= 0:
        assert b.frame_id > a.frame_id, (
            f"two captures report frame ids {a.frame_id} and {b.frame_id}: the second frame is "
            "not a new one")


def _check_stop(c: _Checker, role: str, dev: Any, move_deg: float, within_s: float,
                during_home: bool = False) -> None:
    go = dev.move_to if role == "stage" else dev.set_angle
    start = float(getattr(dev, "position", 0.0) or 0.0)
    if during_home:  # from move_deg away, so homing has a way to go when stop() comes
        if c.rule("stop-during-home", f"moving to {start + move_deg:g}° before homing",
                  lambda: go(start + move_deg)) is None and not c.results[-1].passed:
            return
        c.results.pop()

    def move(target: float) -> None:
        if during_home:
            dev.home()
        else:
            go(target)
    done = threading.Event()
    outcome: list[BaseException | None] = []

    def run() -> None:
        try:
            move(start + move_deg)
            outcome.append(None)
        except BaseException as exc:  # judged below
            outcome.append(exc)
        done.set()

    threading.Thread(target=run, daemon=True).start()
    time.sleep(0.1)
    what = "homing" if during_home else "a move"
    rule = "stop-during-home" if during_home else "stop-interrupts-move"
    t0 = time.perf_counter()
    c.rule("stop-returns-fast", f"stop() during {what}", dev.stop, any_error=True)
    took = time.perf_counter() - t0
    if took > STOP_RETURN_S:
        c.fail("stop-returns-fast", f"stop() took {took:.2f} s (> {STOP_RETURN_S} s); send the "
                                    "stop command and return — the moving call finishes the stop")
    if not done.wait(within_s):
        c.fail(rule, f"{what} was still running {within_s:g} s after stop(); the waiting call "
                     "must notice the stop and return")
        if not done.wait(c.limit_s):
            c.hung = f"{what} after stop()"
        return
    exc = outcome[0] if outcome else None
    if exc is not None and not isinstance(exc, DeviceError):
        c.fail("raises-device-errors", f"the stopped {what} raised {type(exc).__name__}: {exc}")
    else:
        c.results.append(RuleResult(rule, True))


def assert_device_conforms(pm: PluginManager, role: str, name: str,
                           settings: dict[str, Any] | None = None, **options: Any) -> None:
    """Fail (naming every broken rule) unless backend ``name`` passes :func:`check_device`."""
    results = check_device(pm, role, name, settings, **options)
    print(format_results(results, f"{role} backend {name!r}"))  # shown by pytest -rA
    failed = [r for r in results if not r.passed and not r.skipped]
    if failed:
        raise AssertionError(f"{role} backend {name!r} breaks the device contract "
                             "(docs/devices.md):\n" + "\n".join(
                                 f"  rule {r.rule!r}: {r.detail}" for r in failed))


@pytest.fixture
def dotshell_pm() -> PluginManager:
    pm = PluginManager()
    pm.load_entry_points()
    return pm


@pytest.fixture
def serial_emulator(tmp_path: Path) -> Iterator[Callable[..., Any]]:
    """A factory: ``serial_emulator("zaber", speed_deg_s=90)`` → a started emulator."""
    from dotshell.plugins import emulator_class

    started: list[Any] = []

    def start(name: str, **options: Any) -> Any:
        emu = emulator_class(name)(link=tmp_path / f"tty-{name}-{len(started)}", **options)
        started.append(emu.start())
        return emu

    yield start
    for emu in started:
        emu.close()


def assert_backend_conforms(pm: PluginManager, role: str, name: str,
                            settings: dict[str, Any] | None = None, **options: Any) -> Any:
    """Device roles: :func:`assert_device_conforms`. Codings: a :class:`PatternCoding`.
    Exporters: an ``export(run_dir)`` method. Returns the built object (devices: a fresh one,
    not connected)."""
    if role in dv.ROLE_PROTOCOLS:
        assert_device_conforms(pm, role, name, settings, **options)
        return pm.create(role, name, settings, RigContext(), "test")
    obj = pm.create(role, name, settings, None, "test")
    if role == "coding":
        assert isinstance(obj, PatternCoding), f"{name} is not a PatternCoding"
    elif role == "exporter":
        assert callable(getattr(obj, "export", None)), f"{name} has no export(run_dir)"
    return obj
