import importlib.metadata as md

import pytest

from dotshell import hookimpl
from dotshell.backends import Backend
from dotshell.errors import PluginError
from dotshell.plugins import PluginManager


def test_first_party_backends_come_from_entry_points(dotshell_pm):
    assert "graycode" in dotshell_pm.backends("coding")
    for role, name in [("camera", "sim-camera"), ("projector", "sim-projector"),
                       ("stage", "sim-turntable")]:
        info = dotshell_pm.backends(role)[name]
        assert info.plugin == "sim" and info.distribution.startswith("dotshell ")


def test_broken_plugin_is_reported_and_others_still_work(broken_plugin):
    pm = PluginManager()
    pm.load_entry_points()
    [err] = [e for e in pm.load_errors if e.name == "broken"]
    assert err.distribution == "dotshell-broken 1.0"
    assert "ImportError: needs libfoo.so" in err.reason
    assert "graycode" in pm.backends("coding")


def test_strict_mode_makes_a_broken_plugin_fatal(broken_plugin):
    pm = PluginManager(strict=True)
    with pytest.raises(PluginError, match="plugin 'broken' .*needs libfoo.so.*--strict-plugins"):
        pm.load_entry_points()


def test_unknown_backend_lists_valid_choices(dotshell_pm):
    with pytest.raises(PluginError) as e:
        dotshell_pm.backend("coding", "greycode", "p.toml")
    msg = str(e.value)
    assert "p.toml: [coding.backend] = 'greycode'" in msg and "'graycode'" in msg


class _Dup:
    @hookimpl
    def dotshell_codings(self):
        return [Backend("graycode", factory=lambda settings, context: None)]


def test_duplicate_backend_name_keeps_first_and_reports_second(dotshell_pm):
    dotshell_pm.register(_Dup(), name="dup")
    assert dotshell_pm.backends("coding")["graycode"].plugin == "graycode"
    assert any(e.name == "dup" and "already provided" in e.reason for e in dotshell_pm.load_errors)


class _Watcher:
    def __init__(self):
        self.seen = []

    @hookimpl
    def dotshell_view_reconstructed(self, view, n_points):
        self.seen.append((view, n_points))

    @hookimpl
    def dotshell_scan_finished(self, status):
        raise RuntimeError("observer bug")


def test_workflow_hooks_called_with_keywords_and_failures_become_warnings(dotshell_pm):
    w = _Watcher()
    dotshell_pm.register(w, name="watcher")
    assert dotshell_pm.notify("dotshell_view_reconstructed", run_dir="r", view=3, n_points=10) == []
    assert w.seen == [(3, 10)]
    warns = dotshell_pm.notify("dotshell_scan_finished", run_dir="r", status="completed", report={})
    assert warns and "watcher" in warns[0] and "observer bug" in warns[0]
