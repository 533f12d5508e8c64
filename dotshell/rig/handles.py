"""A device as the rig hands it out: calls serialised, time-limited, faults named, a lost device
reconnected once.

Every call a front end or the pipeline makes on ``rig.stage``, ``rig.camera``, ... goes through a
:class:`DeviceHandle`:

* **Serialised.** One lock per device: a front end may poll ``status()`` while a scan moves the
  stage. :meth:`DeviceHandle.poll_status` never waits: while a call runs it returns the last
  snapshot marked ``busy``.
* **Time-limited.** The call runs on the device's own worker thread (always the same thread, so
  SDKs that care about thread affinity are served); the caller waits at most the call's timeout
  (``[ROLE.timeouts]`` in the profile, else :data:`TIMEOUT_DEFAULTS_S`) plus a grace period, then
  gets a :class:`~dotshell.errors.DeviceTimeout` naming the call, the timeout and the key to
  change. The driver sees the same deadline through ``context.time_left()``.
* **Stoppable without the lock.** :meth:`DeviceHandle.stop_now` calls the driver's ``stop()``
  directly on the calling thread — from another thread, or from a signal handler on the main
  thread while that thread waits inside a device call. A call that ends with an error after a
  stop is reported as :class:`~dotshell.errors.DeviceStopped` (never retried).
* **Faults named.** Any exception from plugin code that is not a
  :class:`~dotshell.errors.DotshellError` becomes a :class:`~dotshell.errors.PluginFault`:
  "plugin P (role R, backend B) raised ..." with what the rig was doing (view, angle, run).
* **Stopped after a failed motion.** A ``move_to``/``set_angle``/``home`` that raises, times
  out or faults is followed by the driver's ``stop()`` before any retry, reconnect or close.
* **Reconnected once.** A :class:`~dotshell.errors.DeviceLostError` closes the device, reopens
  it (retrying for ``reconnect_wait_s``) and repeats the call once; with ``reconnect = false``
  it fails at once with a message saying so.
* **Never under a running call.** Nothing closes, reopens or homes a device while a call is
  still inside its driver: the device is told to stop and given :data:`STOP_WAIT_S`; a call
  still running then marks the device lost, with a message naming the plugin and the call.

Properties are read directly (the contract makes them hardware-free) and never take the lock.
"""

from __future__ import annotations

import math
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

from dotshell.backends import RigContext
from dotshell.errors import (DeviceError, DeviceLostError, DeviceStopped, DeviceTimeout,
                             DotshellError, PluginFault)
from dotshell.profile.loader import TIMEOUT_DEFAULTS_S

#: How long past a call's timeout the rig waits for the driver's own timeout error before it
#: declares the device unresponsive (seconds).
GRACE_S = 2.0
#: How often a lost device's port is tried again while it is gone (seconds): a failed open of
#: a missing port costs microseconds, and the scan goes on this soon after it is back.
REOPEN_POLL_S = 0.1
#: Calls whose last arguments are replayed after a reconnect (settings a device forgets).
REPLAYED = ("set_exposure",)
#: Calls that move hardware: when one fails, times out or faults, the device is told to stop
#: before anything else (a retry, a reconnect, a close) happens.
MOTIONS = ("move_to", "set_angle", "home")
#: How long a call still inside its driver may take to end once the device was told to stop
#: (seconds). Past it the device is declared lost and left alone: never closed, reconnected or
#: homed under a call that is still running. This bounds how long closing a rig waits per
#: device, so SIGTERM ends the process within ``STOP_WAIT_S`` per hung device plus the time
#: to save the frames already captured.
STOP_WAIT_S = 2.0
#: Told of every device call as it starts (``enter(label, method, thread_id)``, the native id
#: of the device's thread) and ends (``leave(label)``):
#: the rig server's session worker writes them where the server can read them even when a
#: driver hangs holding the GIL (:mod:`dotshell.server.callboard`). None: nobody listens.
call_watcher: Any = None


@dataclass
class DevicePolicy:
    """How the rig treats one device (from the profile's role section).

    Attributes:
        timeouts_s: per-call timeouts the profile sets (seconds); others use the defaults.
        reconnect: reopen a lost device once before the step fails.
        reconnect_wait_s: how long to keep trying to reopen it (seconds).
        home: ``never``, ``on_connect`` or ``before_scan`` (stages and analyzers).
    """

    timeouts_s: dict[str, float] = field(default_factory=dict)
    reconnect: bool = True
    reconnect_wait_s: float = 10.0
    home: str = "never"

    def timeout(self, method: str) -> tuple[float, bool]:
        """(seconds, whether it is the default) for a call of ``method``."""
        if method in self.timeouts_s:
            return self.timeouts_s[method], False
        if "other" in self.timeouts_s and method not in TIMEOUT_DEFAULTS_S:
            return self.timeouts_s["other"], False
        return TIMEOUT_DEFAULTS_S.get(method, TIMEOUT_DEFAULTS_S["other"]), True


class _Job:
    def __init__(self, fn: Callable[..., Any], args: tuple, kwargs: dict, timeout: float,
                 context: RigContext) -> None:
        self.fn, self.args, self.kwargs = fn, args, kwargs
        self.timeout = timeout
        self.context = context
        self.started = threading.Event()
        self.done = threading.Event()
        self.t_start = math.inf
        self.result: Any = None
        self.error: BaseException | None = None

    def deadline(self) -> float:
        """When the call's timeout runs out (monotonic seconds): its start plus its timeout,
        plus whatever the driver spent in ``context.computing()`` blocks so far."""
        base, extended = self.t_start + self.timeout, self.context.current_deadline()
        return extended if base < extended < math.inf else base

    def overdue(self) -> bool:
        return time.monotonic() > self.deadline() + GRACE_S

    def wait(self) -> bool:
        """Wait for the call to end; False once it is past its (extended) deadline and grace."""
        while not self.done.wait(max(0.0, self.deadline() + GRACE_S - time.monotonic())):
            if self.overdue():
                return self.done.is_set()
        return True

    def run(self) -> None:
        self.t_start = time.monotonic()
        self.context.deadline = self.t_start + self.timeout
        self.started.set()
        try:
            self.result = self.fn(*self.args, **self.kwargs)
        except BaseException as exc:  # handed to the waiting caller
            self.error = exc
        finally:
            self.context.deadline = math.inf
            self.done.set()


class _Worker:
    """The thread one device's calls run on."""

    def __init__(self, name: str) -> None:
        self.jobs: queue.SimpleQueue = queue.SimpleQueue()
        self.current: _Job | None = None
        self.thread = threading.Thread(target=self._run, name=name, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while True:
            job = self.jobs.get()
            if job is None:
                return
            self.current = job
            job.run()
            self.current = None

    def stuck(self) -> _Job | None:
        """The job in progress if it ran past its timeout and grace period."""
        job = self.current
        return job if job is not None and job.overdue() else None

    def shutdown(self) -> None:
        self.jobs.put(None)


class DeviceHandle:
    """One device of a rig behind the rig's rules (see the module docstring). Attribute access
    is forwarded: ``handle.move_to(30)`` runs the driver's ``move_to`` under the rules,
    ``handle.position`` reads the driver's property."""

    _wraps_device = True  # lets dotshell.devices.implements() look at the driver's class

    def __init__(self, role: str, backend: str, plugin: str, distribution: str, device: Any,
                 context: RigContext, policy: DevicePolicy,
                 where: Callable[[], str] = lambda: "") -> None:
        self._role, self._backend = role, backend
        self._plugin, self._distribution = plugin, distribution
        self._device, self._context, self._policy = device, context, policy
        self._where = where
        self._lock = threading.Lock()
        self._worker: _Worker | None = None
        self._stops = 0
        self._lost: BaseException | None = None
        self._snapshot: dict[str, Any] = {}
        self._replay: dict[str, tuple[tuple, dict]] = {}

    # ---- identity -----------------------------------------------------------------------------

    @property
    def _label(self) -> str:
        return f"{self._role} ({self._backend})"

    def __repr__(self) -> str:
        return f"<{self._label}: {self._device!r}>"

    def __dir__(self) -> list[str]:
        return sorted(set(dir(type(self._device))) | set(vars(self._device)))

    # ---- forwarding ---------------------------------------------------------------------------

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        if name == "stop":
            getattr(self._device, "stop")  # noqa: B009 (a probe: AttributeError if it cannot stop)
            return self.stop_now
        try:
            value = getattr(self._device, name)
        except (AttributeError, DotshellError):
            raise
        except Exception as exc:  # a property that broke the contract
            raise self._fault(f"reading .{name}", exc) from exc
        if not callable(value):
            return value

        def call(*args: Any, **kwargs: Any) -> Any:
            return self.call(name, *args, **kwargs)

        call.__name__ = name
        call.__doc__ = getattr(value, "__doc__", None)
        return call

    # ---- calls --------------------------------------------------------------------------------

    def call(self, method: str, *args: Any, **kwargs: Any) -> Any:
        """Run ``device.method(*args, **kwargs)`` under the rig's rules."""
        with self._lock:
            stops = self._stops
            try:
                if self._lost is not None and method not in ("connect", "close"):
                    raise DeviceLostError(f"{self._label} stopped answering earlier: "
                                          f"{self._lost}")
                result = self._run(method, args, kwargs)
            except (DeviceError, PluginFault) as exc:
                if method in MOTIONS:
                    self._halt_after_failure(already_stopped=self._stops != stops)
                if self._stops != stops and isinstance(exc, DeviceError):
                    raise DeviceStopped(f"{self._label} was stopped during {method}(): "
                                        f"{exc}") from None
                if isinstance(exc, DeviceLostError) and method not in ("connect", "close"):
                    return self._recover(method, args, kwargs, exc)
                raise
            if method in REPLAYED:
                self._replay[method] = (args, kwargs)
            return result

    def _run(self, method: str, args: tuple, kwargs: dict) -> Any:
        watcher = call_watcher
        if watcher is None:
            return self._run_watched(method, args, kwargs)
        watcher.enter(self._label, method, self._ensure_worker().thread.native_id)
        try:
            return self._run_watched(method, args, kwargs)
        finally:
            watcher.leave(self._label)

    def _run_watched(self, method: str, args: tuple, kwargs: dict) -> Any:
        timeout, default = self._policy.timeout(method)
        fn = getattr(self._device, method)
        job = _Job(fn, args, kwargs, timeout, self._context)
        worker = self._ensure_worker()
        worker.jobs.put(job)
        while not job.started.wait(0.25):  # a call left running (e.g. after Ctrl-C) goes first
            stuck = worker.stuck()
            if stuck is not None:
                self._lost = DeviceTimeout(self._timeout_text(stuck.fn.__name__, stuck.timeout,
                                                              None))
                raise self._lost
        if not job.wait():
            self._lost = DeviceTimeout(self._timeout_text(method, timeout, default))
            raise self._lost
        if job.error is None:
            return job.result
        if isinstance(job.error, (DotshellError, MemoryError)):  # not a bug of the plugin
            raise job.error
        if isinstance(job.error, Exception):
            raise self._fault(f"{method}()", job.error) from job.error
        raise job.error  # SystemExit and the like from plugin code: not ours to swallow

    def _timeout_text(self, method: str, timeout: float, default: bool | None) -> str:
        key = f"[{self._role}.timeouts] {method if method in TIMEOUT_DEFAULTS_S else 'other'}"
        how = ("" if default is None else " (the default)" if default else
               f" (set by {key} in the profile)")
        where = self._where()
        return (f"{self._label} did not finish {method}() within {timeout:g} s{how}"
                f"{' ' + where if where else ''}. Check that it is powered and connected; if "
                f"it is just slow, raise {key} = SECONDS in the profile.")

    def _fault(self, doing: str, exc: BaseException) -> PluginFault:
        where = self._where()
        return PluginFault(
            f"plugin {self._plugin!r} (role {self._role}, backend {self._backend}) raised "
            f"{type(exc).__name__}: {exc} in {doing}{' ' + where if where else ''}. This is a "
            f"bug in the plugin ({self._distribution}); report it to its authors with this "
            "message. Frames captured so far are kept.")

    def _ensure_worker(self) -> _Worker:
        if self._worker is None:
            self._worker = _Worker(f"dotshell-{self._role}")
        return self._worker

    # ---- lost devices -------------------------------------------------------------------------

    def _recover(self, method: str, args: tuple, kwargs: dict, exc: DeviceError) -> Any:
        if not self._policy.reconnect:
            raise DeviceLostError(
                f"{self._label} was lost during {method}(): {exc} [{self._role}] reconnect = "
                "false, so the step fails; reconnect the device (or set reconnect = true) and "
                "run again.") from None
        wait = self._policy.reconnect_wait_s
        self._context.log.warn(f"lost during {method}(): {exc} — reconnecting (waiting up to "
                               f"{wait:g} s)")
        self._reopen(wait, exc)
        self._context.log.info("reconnected")
        try:
            return self._run(method, args, kwargs)
        except DeviceLostError as again:
            self._lost = again
            raise DeviceLostError(f"{self._label} was lost again right after reconnecting, in "
                                  f"{method}(): {again}") from None

    def _reopen(self, wait_s: float, why: BaseException) -> None:
        """Close the device (directly if its worker is stuck) and connect it again, trying for
        ``wait_s`` seconds; replays remembered settings and homes if the policy says so."""
        self._close_for_reopen()
        deadline = time.monotonic() + wait_s
        last: BaseException = why
        while True:
            try:
                self._run("connect", (), {})
                break
            except PluginFault:
                raise
            except DeviceError as exc:
                last = exc
            if time.monotonic() >= deadline:
                self._lost = last
                raise DeviceLostError(
                    f"{self._label} was lost ({why}) and did not come back within {wait_s:g} s "
                    f"(last error: {last}). Check its cable and power; raise "
                    f"[{self._role}] reconnect_wait_s to wait longer.") from None
            time.sleep(min(REOPEN_POLL_S, max(0.0, deadline - time.monotonic())))
        self._lost = None
        for method, (args, kwargs) in self._replay.items():
            self._run(method, args, kwargs)
        if self._policy.home == "on_connect" and hasattr(self._device, "home"):
            self._run("home", (), {})

    def _close_for_reopen(self) -> None:
        if not self._settle():
            raise self._still_inside()
        try:
            self._run("close", (), {})
        except Exception:  # closing a lost device may fail; reconnecting is what matters
            pass

    # ---- calls still inside the driver --------------------------------------------------------

    def _stop_driver(self) -> None:
        """The driver's ``stop()`` if it has one (not counted as a user's stop); never raises."""
        stop = getattr(self._device, "stop", None)
        if callable(stop):
            try:
                stop()
            except BaseException:  # stopping must not mask what went wrong
                pass

    def _settle(self) -> bool:
        """True once no call is inside the driver: if one is, the device is told to stop and
        the call given :data:`STOP_WAIT_S` to end."""
        worker = self._worker
        current = worker.current if worker is not None else None
        if current is None:
            return True
        self._stop_driver()
        return current.done.wait(STOP_WAIT_S)

    def _still_inside(self) -> DeviceLostError:
        worker = self._worker
        current = worker.current if worker is not None else None
        name = current.fn.__name__ if current is not None else "a call"
        since = time.monotonic() - current.t_start if current is not None else 0.0
        return DeviceLostError(
            f"{self._label}: plugin {self._plugin!r} ({self._distribution}) is still inside "
            f"{name}() after {since:.0f} s, {STOP_WAIT_S:g} s after it was told to stop; the "
            "device is left alone (not closed, reconnected or homed under a running call). "
            "Check the device, power-cycle it and start dotshell again; report the hang to the "
            "plugin's authors.")

    def _halt_after_failure(self, already_stopped: bool) -> None:
        """A motion failed, timed out or faulted: stop the device before anything else (unless
        a stop ended it); if the call is still inside the driver after that, the device is lost
        (no retry)."""
        if not self._settle():
            self._lost = self._still_inside()
            raise self._lost
        if not already_stopped:
            self._stop_driver()

    # ---- rig-side operations ------------------------------------------------------------------

    @property
    def lost(self) -> bool:
        """True when the device stopped answering and was not recovered."""
        return self._lost is not None

    def reopen(self) -> None:
        """Close and connect again (a session's connect() on a lost device)."""
        with self._lock:
            self._reopen(self._policy.reconnect_wait_s, self._lost or DeviceLostError("lost"))

    def stop_now(self) -> None:
        """Call the driver's ``stop()`` now, on this thread, without the device lock. Never
        raises, logs nothing (safe in a signal handler)."""
        self._stops += 1
        try:
            self._device.stop()
        except BaseException:  # stopping must reach every device
            pass

    def poll_status(self) -> dict[str, Any]:
        """``status()`` without waiting: while another call runs, the last snapshot with
        ``busy`` naming that call."""
        if not self._lock.acquire(blocking=False):
            worker = self._worker
            current = worker.current if worker is not None else None
            busy = current.fn.__name__ if current is not None else "a call"
            return {**self._snapshot, "busy": busy}
        try:
            if self._lost is not None:
                return {**self._snapshot, "error": f"lost: {self._lost}"}
            self._snapshot = dict(self._run("status", (), {}))
            return self._snapshot
        except Exception as exc:
            return {**self._snapshot, "error": f"{type(exc).__name__}: {exc}"}
        finally:
            self._lock.release()

    def release(self) -> None:
        """End the worker thread without closing the device (it was never connected)."""
        worker, self._worker = self._worker, None
        if worker is not None:
            worker.shutdown()

    def shutdown(self) -> None:
        """Close the device (directly if a call is stuck) and end its worker thread."""
        if not self._settle():
            self._lost = self._still_inside()  # left alone: its thread is abandoned below
            self.release()
            return
        with self._lock:
            try:
                self._run("close", (), {})
            except Exception:  # closing must not mask the original error
                pass
        self.release()
        self._lost = None


def unwrap(obj: Any) -> Any:
    """The driver object behind a :class:`DeviceHandle` (anything else is returned as is)."""
    return obj._device if isinstance(obj, DeviceHandle) else obj
