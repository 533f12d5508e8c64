"""The rig's device handles: calls serialised per device, per-call timeouts named with the
profile key, plugin exceptions wrapped, lost devices reconnected once, stop() without the lock
(also from a signal handler while the main thread is inside a device call)."""

import signal
import threading
import time

import pytest

import dotshell.rig.handles as handles
from dotshell.backends import RigContext
from dotshell.errors import (DeviceError, DeviceLostError, DeviceStopped, DeviceTimeout,
                             PluginFault)
from dotshell.rig.handles import DeviceHandle, DevicePolicy


class Gadget:
    """A test device: counts concurrent calls, can hang, fail, get lost, move slowly."""

    def __init__(self):
        self.active = 0
        self.most_active = 0
        self.connects = 0
        self.hang_s = 0.0
        self.lose_next = 0
        self.halt = threading.Event()
        self.threads = set()

    def connect(self):
        self.connects += 1

    def close(self):
        pass

    def status(self):
        return {"ok": True}

    def work(self, seconds=0.0):
        self.threads.add(threading.get_ident())
        self.active += 1
        self.most_active = max(self.most_active, self.active)
        try:
            time.sleep(seconds or self.hang_s)
            if self.lose_next:
                self.lose_next -= 1
                raise DeviceLostError("gadget on /dev/ttyX: the port failed (EIO)")
            return "done"
        finally:
            self.active -= 1

    def boom(self):
        return 1 / 0

    def move_to(self, degrees):
        self.halt.clear()
        t0 = time.monotonic()
        while time.monotonic() - t0 < 5.0:
            if self.halt.wait(0.005):
                raise DeviceError("gadget: stopped")
        return degrees

    def stop(self):
        self.halt.set()


def handle(dev=None, where="", **policy):
    dev = dev or Gadget()
    ctx = RigContext().for_device("stage", "gadget")
    lines = []
    ctx.log.listen(lambda level, text, when: lines.append((level, text)))
    h = DeviceHandle("stage", "gadget", "testplug", "testdist 1.0", dev, ctx,
                     DevicePolicy(**policy), lambda: where)
    h.lines = lines
    return h, dev


def test_calls_are_serialised_and_run_on_one_device_thread():
    h, dev = handle()
    threads = [threading.Thread(target=h.work, args=(0.05,)) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert dev.most_active == 1
    assert len(dev.threads) == 1 and threading.get_ident() not in dev.threads


def test_status_poll_never_waits_for_a_call_in_progress():
    h, dev = handle()
    assert h.poll_status() == {"ok": True}
    t = threading.Thread(target=h.work, args=(0.5,))
    t.start()
    time.sleep(0.05)
    t0 = time.perf_counter()
    snap = h.poll_status()
    took = time.perf_counter() - t0
    t.join()
    assert snap == {"ok": True, "busy": "work"} and took < 0.05


def test_plugin_exception_becomes_plugin_fault_naming_plugin_role_backend_and_where():
    h, _ = handle(where="(view 3, angle 90°, run runs/x)")
    with pytest.raises(PluginFault) as info:
        h.boom()
    text = str(info.value)
    assert "plugin 'testplug' (role stage, backend gadget) raised ZeroDivisionError" in text
    assert "in boom() (view 3, angle 90°, run runs/x)" in text and "testdist 1.0" in text
    assert info.value.exit_code == 2


def test_timeout_names_the_call_the_default_and_the_profile_key(monkeypatch):
    monkeypatch.setattr(handles, "GRACE_S", 0.05)
    monkeypatch.setitem(handles.TIMEOUT_DEFAULTS_S, "other", 0.2)
    h, dev = handle()
    dev.hang_s = 1.0
    t0 = time.perf_counter()
    with pytest.raises(DeviceTimeout, match=r"stage \(gadget\) did not finish work\(\) within "
                       r"0.2 s \(the default\).*raise \[stage.timeouts\] other = SECONDS"):
        h.work()
    assert time.perf_counter() - t0 < 0.6


def test_profile_timeout_then_the_unresponsive_device_is_reconnected(monkeypatch):
    monkeypatch.setattr(handles, "GRACE_S", 0.05)
    h, dev = handle(timeouts_s={"move_to": 0.1})
    with pytest.raises(DeviceTimeout, match=r"within 0.1 s \(set by \[stage.timeouts\] move_to"):
        h.move_to(10)
    assert h.lost
    dev.stop()  # the stuck call ends; the next call reopens the device first
    assert h.work(0.01) == "done"
    assert dev.connects == 1 and not h.lost
    assert any("reconnecting" in text for _, text in h.lines)


def test_lost_device_is_reconnected_once_and_the_call_repeated():
    h, dev = handle(reconnect=True, reconnect_wait_s=1.0)
    dev.lose_next = 1
    assert h.work(0.01) == "done"
    assert dev.connects == 1
    assert [level for level, _ in h.lines] == ["warning", "info"]
    assert "lost during work()" in h.lines[0][1] and h.lines[1][1].endswith("reconnected")


def test_lost_twice_fails_with_a_clear_message():
    h, dev = handle(reconnect=True, reconnect_wait_s=1.0)
    dev.lose_next = 2
    with pytest.raises(DeviceLostError, match="lost again right after reconnecting"):
        h.work(0.01)


def test_reconnect_off_fails_at_once_saying_so():
    h, dev = handle(reconnect=False)
    dev.lose_next = 1
    with pytest.raises(DeviceLostError, match=r"reconnect = false, so the step fails"):
        h.work(0.01)
    assert dev.connects == 0


def test_stop_from_another_thread_does_not_wait_for_the_lock():
    h, dev = handle()
    threading.Timer(0.1, h.stop).start()
    t0 = time.perf_counter()
    with pytest.raises(DeviceStopped, match="was stopped during move_to"):
        h.move_to(90)
    assert time.perf_counter() - t0 < 0.5


def test_stop_from_a_signal_handler_while_the_main_thread_is_inside_the_call():
    h, dev = handle()
    fired = []

    def on_alarm(signum, frame):
        fired.append(time.perf_counter())
        h.stop()

    old = signal.signal(signal.SIGALRM, on_alarm)
    try:
        signal.setitimer(signal.ITIMER_REAL, 0.15)
        with pytest.raises(DeviceStopped):
            h.move_to(90)
        ended = time.perf_counter()
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    assert fired and ended - fired[0] < 0.5


class Renderer:
    """A simulated device: its frames are computed by the host (``context.computing()``) or it
    stalls like hardware; both end only when the test releases them."""

    def __init__(self, context):
        self.context = context
        self.release = threading.Event()

    def connect(self):
        pass

    def close(self):
        self.release.set()

    def render(self):
        with self.context.computing():
            self.release.wait()
        return "frame"

    def stall(self):
        self.release.wait()
        return "frame"


def _past_the_deadline(h, method, timeout_s):
    """Call ``method`` in a thread; release the device once the call has run past its timeout
    and grace (a lower bound on time, never an upper one); return (result, error)."""
    out = {}

    def go():
        try:
            out["result"] = getattr(h, method)()
        except Exception as exc:
            out["error"] = exc

    dev = h._device
    t = threading.Thread(target=go)
    t0 = time.monotonic()
    t.start()
    while time.monotonic() < t0 + timeout_s + handles.GRACE_S + 0.2 and t.is_alive():
        t.join(0.05)
    dev.release.set()
    t.join()
    return out.get("result"), out.get("error")


def test_a_devices_own_computing_time_never_counts_against_its_timeout(monkeypatch):
    """Issue 33: a simulated camera rendering on a busy host must not time out; a device that
    really stalls still does, with the same timeout."""
    monkeypatch.setattr(handles, "GRACE_S", 0.05)
    ctx = RigContext().for_device("camera", "renderer")
    policy = DevicePolicy(timeouts_s={"other": 0.1})
    h = DeviceHandle("camera", "renderer", "p", "d", Renderer(ctx), ctx, policy)
    result, error = _past_the_deadline(h, "render", 0.1)
    assert error is None and result == "frame"
    ctx = RigContext().for_device("camera", "renderer")
    h = DeviceHandle("camera", "renderer", "p", "d", Renderer(ctx), ctx, policy)
    result, error = _past_the_deadline(h, "stall", 0.1)
    assert isinstance(error, DeviceTimeout) and "did not finish stall() within 0.1 s" in str(error)


def test_computing_outside_a_rig_call_changes_nothing():
    ctx = RigContext()
    with ctx.computing():
        pass
    assert ctx.time_left() == float("inf")
