"""Kit v2 (dotshell.testing, issue 28): a hanging call fails `returns-in-time` and the kit goes
on (the rules after it listed as skipped), a None frame is named as such, stale frame metadata
is caught, a prepare hook runs before the rules, and the failure paths — stop during homing, a
lost device, a deadline on a stuck device — are checked on the shipped Zaber emulator through
the author's own fault switches."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from dotshell import hookimpl
from dotshell.backends import Backend
from dotshell.devices import FrameInfo
from dotshell.errors import DeviceError
from dotshell.plugins import PluginManager
from dotshell.testing import assert_device_conforms, check_device, format_results
from test_conformance import GoodCamera


class HangingCamera(GoodCamera):
    release = threading.Event()

    def capture(self):
        if self.connected:
            self.release.wait()  # a driver stuck in an SDK call
        return super().capture()


class NoneCamera(GoodCamera):
    def capture(self):
        super().capture()
        return None  # a driver that lost its frame and did not say so


class StaleInfoCamera(GoodCamera):
    def last_frame_info(self):
        return FrameInfo(timestamp_s=1000.0, frame_id=7)  # the same frame every time


class HomeIgnoresStop:
    """A stage whose home() goes on for 3 s whatever stop() says."""

    def __init__(self, settings=None, context=None):
        self.connected, self._angle = False, 0.0

    def connect(self):
        self.connected = True

    def close(self):
        self.connected = False

    def status(self):
        return {}

    @property
    def position(self):
        return self._angle

    def move_to(self, degrees):
        if not self.connected or not np.isfinite(degrees):
            raise DeviceError("no")
        self._angle = float(degrees)

    def stop(self):
        pass

    def home(self):
        time.sleep(3.0)
        self._angle = 0.0


class Plugin:
    @hookimpl
    def dotshell_cameras(self):
        return [Backend("hangs", HangingCamera, {}), Backend("none", NoneCamera, {}),
                Backend("stale", StaleInfoCamera, {}), Backend("good", GoodCamera, {})]

    @hookimpl
    def dotshell_stages(self):
        return [Backend("home-ignores-stop", HomeIgnoresStop, {})]


@pytest.fixture
def kit_pm():
    pm = PluginManager()
    pm.register(Plugin(), name="kit-v2")
    return pm


def test_a_hanging_capture_fails_returns_in_time_and_the_kit_goes_on(kit_pm):
    try:
        results = check_device(kit_pm, "camera", "hangs", call_limit_s=0.5)
    finally:
        HangingCamera.release.set()
    by_rule = {r.rule: r for r in results}
    assert not by_rule["returns-in-time"].passed
    assert "capture() did not return within 0.5 s" in by_rule["returns-in-time"].detail
    skipped = [r for r in results if r.skipped]
    assert skipped and all("capture() never returned" in r.detail for r in skipped)
    listing = format_results(results, "camera backend 'hangs'")
    assert "FAIL returns-in-time" in listing and "skip " in listing


def test_a_none_frame_is_named_as_such(kit_pm):
    with pytest.raises(AssertionError, match=r"rule 'capture-not-none': capture\(\) returned "
                                             r"None \(no frame\)"):
        assert_device_conforms(kit_pm, "camera", "none")


def test_stale_frame_metadata_is_caught(kit_pm):
    results = check_device(kit_pm, "camera", "stale")
    [stale] = [r for r in results if r.rule == "frame-info-advances"]
    assert not stale.passed and "not newer (a stale or repeated frame)" in stale.detail


def test_the_prepare_hook_runs_on_the_connected_device(kit_pm, capsys):
    prepared = []
    assert_device_conforms(kit_pm, "camera", "good",
                           prepare=lambda dev: prepared.append(dev.connected))
    assert prepared == [True]
    listing = capsys.readouterr().out
    assert "rules passed" in listing and "ok   prepare" in listing


def test_a_home_that_ignores_stop_fails_stop_during_home(kit_pm):
    results = check_device(kit_pm, "stage", "home-ignores-stop", stop_within_s=0.5)
    [rule] = [r for r in results if r.rule == "stop-during-home"]
    assert not rule.passed and "homing was still running 0.5 s after stop()" in rule.detail


def test_zaber_passes_the_failure_path_rules_through_its_emulator_faults(dotshell_pm,
                                                                        serial_emulator):
    emu = serial_emulator("zaber", speed_deg_s=360.0)
    faults = {"stuck": lambda: setattr(emu.faults, "stuck", True), "lost": emu.unplug}
    prepared = []
    results = check_device(dotshell_pm, "stage", "zaber", {"port": emu.port},
                           prepare=lambda dev: prepared.append(dev.home()), faults=faults)
    assert [str(r) for r in results if not r.passed] == []
    assert {"stop-during-home", "deadline-respected", "lost-device", "prepare",
            "returns-in-time"} - {r.rule for r in results} == {"returns-in-time"}
    assert prepared == [None]
