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


# ---- third-party plugins that misbehave (issue: runs that never lie) ---------------------------

from conftest import make_dist  # noqa: E402


def _install(tmp_path, monkeypatch, dist, module, source, ep_name):
    path = make_dist(tmp_path / dist, dist, module, source, ep_name)
    monkeypatch.syspath_prepend(str(path))


SIM_CAMERA_TWIN = '''
from dotshell import hookimpl
from dotshell.backends import Backend

@hookimpl
def dotshell_cameras():
    return [Backend("sim-camera", lambda settings, context: None, {}, "an impostor")]
'''


def test_a_third_party_duplicate_never_takes_over_and_is_reported_at_start(
        tmp_path, monkeypatch, capsys):
    from dotshell.cli.app import main

    _install(tmp_path, monkeypatch, "dotshell-twin", "dotshell_twin_mod", SIM_CAMERA_TWIN, "twin")
    pm = PluginManager()
    pm.load_entry_points()
    assert pm.backends("camera")["sim-camera"].plugin == "sim"  # first party wins
    assert pm.backend("camera", "twin:sim-camera").plugin == "twin"  # still choosable
    [err] = [e for e in pm.load_errors if e.name == "twin"]
    assert "already provided by plugin 'sim'" in err.reason and "twin:sim-camera" in err.reason
    assert main(["plugins"]) == 1  # every command shows it at start-up
    assert "twin:sim-camera" in capsys.readouterr().err


def test_an_entry_point_named_like_a_first_party_one_does_not_hide_it(tmp_path, monkeypatch):
    _install(tmp_path, monkeypatch, "dotshell-shadow", "dotshell_shadow_mod",
             SIM_CAMERA_TWIN.replace('"sim-camera"', '"shadow-camera"'), "sim")
    pm = PluginManager()
    pm.load_entry_points()
    assert pm.backends("camera")["sim-camera"].plugin == "sim"  # ours still loaded
    assert pm.backends("camera")["shadow-camera"].plugin == "sim@dotshell-shadow"
    assert any("entry-point name 'sim' is already taken" in e.reason for e in pm.load_errors)


@pytest.mark.parametrize("source,why", [
    ("import sys\nsys.exit(3)\n", "SystemExit: 3"),
    ("raise KeyboardInterrupt\n", "KeyboardInterrupt"),
])
def test_exiting_at_import_is_contained(tmp_path, monkeypatch, source, why):
    from dotshell.cli.app import main

    _install(tmp_path, monkeypatch, "dotshell-exit", "dotshell_exit_mod", source, "exits")
    pm = PluginManager()
    pm.load_entry_points()
    [err] = [e for e in pm.load_errors if e.name == "exits"]
    assert why in err.reason and "sim-camera" in pm.backends("camera")
    assert main(["check", "profiles/sim-metal-cylinder.toml"]) == 0


@pytest.mark.parametrize("returned", ["'not a list'", "[42]", "[Backend('', None)]",
                                      "[Backend('x', lambda **k: 1, {'k': 3})]"])
def test_a_backend_hook_returning_the_wrong_type_is_that_plugins_load_error(
        tmp_path, monkeypatch, returned):
    src = ("from dotshell import hookimpl\nfrom dotshell.backends import Backend\n"
           f"@hookimpl\ndef dotshell_stages():\n    return {returned}\n")
    _install(tmp_path, monkeypatch, "dotshell-wrong", "dotshell_wrong_mod", src, "wrong")
    pm = PluginManager()
    pm.load_entry_points()
    [err] = [e for e in pm.load_errors if e.name == "wrong"]
    assert "must return a list of dotshell.backends.Backend" in err.reason
    assert "sim-turntable" in pm.backends("stage")


def test_a_factory_raising_is_named_with_plugin_role_backend_and_exit_2(
        tmp_path, monkeypatch, capsys):
    from conftest import small_profile_dict, write_profile
    from dotshell.cli.app import main

    src = ("from dotshell import hookimpl\nfrom dotshell.backends import Backend\n"
           "def boom(settings, context):\n    raise ZeroDivisionError('driver bug')\n"
           "@hookimpl\ndef dotshell_stages():\n    return [Backend('boom-stage', boom)]\n")
    _install(tmp_path, monkeypatch, "dotshell-boom", "dotshell_boom_mod", src, "boom")
    raw = small_profile_dict(views=2)
    raw["stage"] = {"backend": "boom-stage"}
    prof = write_profile(tmp_path / "p.toml", raw)
    assert main(["scan", str(prof), "--out", str(tmp_path / "runs")]) == 2
    err = capsys.readouterr().err
    assert "plugin 'boom'" in err and "role stage" in err and "'boom-stage'" in err
    assert "ZeroDivisionError" in err and "Traceback" not in err


def test_a_hanging_workflow_hook_is_named_and_the_workflow_goes_on(dotshell_pm):
    import threading

    gate = threading.Event()

    class Hangs:
        @hookimpl
        def dotshell_view_captured(self, view):
            gate.wait(30)

    dotshell_pm.register(Hangs(), name="hangs")
    dotshell_pm.hook_timeout_s = 0.2
    warnings = dotshell_pm.notify("dotshell_view_captured", run_dir="r", view=0, angle_deg=0.0,
                                  n_frames=1)
    gate.set()
    assert warnings == ["plugin 'hangs' did not return within 0.2 s in dotshell_view_captured; "
                        "the workflow went on without it"]
