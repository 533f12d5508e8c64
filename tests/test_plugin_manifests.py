"""Backends declared as data (each plugin's ``dotshell.toml``) and imported only when used:
light commands import no driver, a broken backend is named when it is loaded, plugins without
a manifest load as before."""

from __future__ import annotations

import json
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from conftest import ROOT, small_profile_dict, write_profile
from dotshell.cli.app import main
from dotshell.errors import PluginError
from dotshell.plugins import PluginManager

FIRST_PARTY = ("dotshell_sim", "dotshell_codings", "dotshell_meshing", "dotshell_dotio",
               "dotshell_normalizers", "dotshell_serial", "dotshell_projectors", "dotshell_cameras")

#: what a command that uses no device must not import: the drivers, their libraries, the meshers
HEAVY = ("cv2", "serial", "usb", "open3d", "numpy", "harvesters", "pylablib", "pyglet")


def _modules_after(argv: list[str], tmp_path: Path) -> tuple[list[str], str]:
    """The modules a fresh interpreter holds after ``dotshell ARGV`` (run in-process there),
    and what the command printed."""
    dump = tmp_path / "modules.json"
    code = (
        "import json, sys\n"
        "from dotshell.cli.app import main\n"
        "try:\n"
        f"    main({argv!r})\n"
        "except SystemExit:\n"
        "    pass\n"
        f"open({str(dump)!r}, 'w').write(json.dumps(sorted(sys.modules)))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=120, cwd=tmp_path, env={**_env(tmp_path)})
    assert dump.exists(), r.stderr
    return json.loads(dump.read_text()), r.stdout


def _env(tmp_path: Path) -> dict[str, str]:
    import os

    # a runtime directory of its own: `status` finds no server of another test
    return {**os.environ, "XDG_RUNTIME_DIR": str(tmp_path), "COLUMNS": "200"}


@pytest.mark.parametrize("argv", [["--help"], ["status"], ["plugins"]])
def test_light_commands_import_no_driver(argv, tmp_path):
    modules, printed = _modules_after(argv, tmp_path)
    heavy = [m for m in modules if m.split(".")[0] in HEAVY]
    plugin_code = [m for m in modules if m.split(".")[0] in FIRST_PARTY]
    assert heavy == [] and plugin_code == [], (heavy, plugin_code)
    if argv == ["plugins"]:  # still every backend, from the manifests
        for name in ("sim-camera", "opencv", "genicam", "grbl", "elliptec", "lightcrafter4500",
                     "graycode-phase", "open3d-poisson", "tetgen", "diffuse-fresnel", "toast"):
            assert name in printed


def test_a_profile_imports_only_the_backends_it_uses(tmp_path):
    p = write_profile(tmp_path / "p.toml", small_profile_dict())
    modules, printed = _modules_after(["check", str(p)], tmp_path)
    assert "profile OK" in printed
    assert "dotshell_sim.devices" in modules and "dotshell_codings.graycode" in modules
    for unused in ("dotshell_cameras.opencv", "dotshell_serial.grbl", "serial",
                   "dotshell_projectors.lightcrafter", "dotshell_meshing.surface", "open3d",
                   "dotshell_codings.xor", "dotshell_dotio.nirfast"):
        assert unused not in modules, unused


def test_every_first_party_package_ships_a_manifest_its_backends_match():
    pm = PluginManager()
    pm.load_entry_points()
    declared = {(b["kind"], b["name"]) for package in FIRST_PARTY for b in tomllib.loads(
        (ROOT / "plugins" / package / "dotshell.toml").read_text())["backends"]}
    assert pm.check_backends() == [] and pm.load_errors == []
    listed = {(role, name) for role in pm.qualified for name in pm.backends(role)}
    assert declared <= listed and len(declared) >= 31
    for role, name in declared:
        info = pm.backend(role, name)
        assert info.loaded and info.plugin in pm.manifests and info.backend.name == name
        assert info.backend.summary == info.summary != ""


# ---- a plugin of one's own, with a manifest -----------------------------------------------------

def _install(site: Path, package: str, manifest: str, modules: dict[str, str],
             ep: str = "mine") -> None:
    """A distribution installed by hand: a dist-info with one ``dotshell`` entry point to the
    package ``package``, which holds ``dotshell.toml`` and ``modules``."""
    info = site / f"dotshell_{ep}-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: dotshell-{ep}\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(f"[dotshell]\n{ep} = {package}\n")
    pkg = site / package
    pkg.mkdir()
    (pkg / "__init__.py").write_text("raise ImportError('the package itself is never imported')\n"
                                     if "__init__" not in modules else modules.pop("__init__"))
    (pkg / "dotshell.toml").write_text(manifest)
    for name, source in modules.items():
        (pkg / f"{name}.py").write_text(source)


GOOD = '''
from dotshell.backends import Backend
from dotshell.settings import Setting

class Exporter:
    def __init__(self, settings):
        self.settings = settings

    def export(self, run_dir):
        return []

XYZ = Backend("mine-xyz", lambda settings, context=None: Exporter(settings),
              {"digits": Setting("int", 3, "digits")})
'''

MANIFEST = '''
[[backends]]
kind = "exporter"
name = "mine-xyz"
summary = "an exporter of my own"
python_name = "mine_pkg.good:XYZ"

[[backends]]
kind = "camera"
name = "mine-cam"
summary = "a camera whose driver needs a library that is missing"
python_name = "mine_pkg.broken:BACKEND"
'''


@pytest.fixture
def my_plugin(tmp_path, monkeypatch):
    site = tmp_path / "site"
    _install(site, "mine_pkg", MANIFEST, {
        "__init__": "", "good": GOOD,
        "broken": "raise ImportError('needs libcam.so, which is not installed')\n"})
    monkeypatch.syspath_prepend(str(site))
    for name in [m for m in sys.modules if m.startswith("mine_pkg")]:
        monkeypatch.delitem(sys.modules, name)
    return site


def test_manifest_backends_are_listed_unloaded_and_import_on_use(my_plugin):
    pm = PluginManager()
    pm.load_entry_points()
    assert pm.load_errors == [] and "mine_pkg.good" not in sys.modules
    info = pm.backend("exporter", "mine-xyz")
    assert (info.plugin, info.distribution, info.summary) == ("mine", "dotshell-mine 1.0",
                                                             "an exporter of my own")
    assert not info.loaded
    exporter = pm.create("exporter", "mine-xyz", {"digits": 5})
    assert exporter.settings == {"digits": 5} and "mine_pkg.good" in sys.modules
    assert "mine_pkg.broken" not in sys.modules  # the other backend was never touched


def test_broken_manifest_backend_is_named_when_used(my_plugin):
    pm = PluginManager()
    pm.load_entry_points()
    assert pm.load_errors == [] and "mine-cam" in pm.backends("camera")
    with pytest.raises(PluginError) as e:
        pm.create("camera", "mine-cam", {})
    text = str(e.value)
    assert "plugin 'mine' (dotshell-mine 1.0) failed to load its camera backend 'mine-cam'" in text
    assert "ImportError: needs libcam.so" in text and "mine_pkg/broken.py:1" in text
    [failure] = pm.check_backends()
    assert failure.name == "mine" and "needs libcam.so" in failure.reason


def test_plugins_check_names_the_broken_backend_and_exits_2(my_plugin, capsys):
    assert main(["plugins"]) == 0  # listing imports nothing, so nothing is broken yet
    out = capsys.readouterr().out
    assert "mine-cam" in out and "mine-xyz" in out
    assert main(["plugins", "--check"]) == 2
    out = " ".join(capsys.readouterr().out.split())
    assert "backends that failed to load:" in out and "'mine-cam'" in out
    assert "needs libcam.so" in out and "'mine-xyz'" not in out.split("failed to load:")[1]
    assert main(["--strict-plugins", "plugins"]) == 2
    assert "needs libcam.so" in " ".join(capsys.readouterr().err.split())


@pytest.mark.parametrize("entry, says", [
    ('kind = "scanner"\nname = "x"\npython_name = "m:x"', "kind = 'scanner' is not a role"),
    ('kind = "camera"\nname = "x"\npython_name = "m.x"', 'must be "package.module:attribute"'),
    ('kind = "camera"\npython_name = "m:x"', 'needs name = "..."'),
    ('kind = "camera"\nname = "x"\npython_name = "m:x"\nfactory = "f"', "unknown key 'factory'"),
])
def test_malformed_manifest_is_a_load_error_naming_the_file(tmp_path, monkeypatch, entry, says):
    site = tmp_path / "site"
    _install(site, "bad_pkg", f"[[backends]]\n{entry}\n", {}, ep="bad")
    monkeypatch.syspath_prepend(str(site))
    pm = PluginManager()
    pm.load_entry_points()
    [err] = [e for e in pm.load_errors if e.name == "bad"]
    assert "bad_pkg/dotshell.toml: [[backends]] #1" in err.reason and says in err.reason
    assert "graycode" in pm.backends("coding")  # the others still load


def test_plugin_without_manifest_is_loaded_eagerly_as_before(tmp_path, monkeypatch):
    from conftest import make_dist

    source = ("from dotshell import hookimpl\n" + GOOD + "\n@hookimpl\n"
              "def dotshell_exporters():\n    return [XYZ]\n")
    site = make_dist(tmp_path / "site", "dotshell-old", "old_style_plugin", source, "old")
    monkeypatch.syspath_prepend(str(site))
    pm = PluginManager()
    pm.load_entry_points()
    info = pm.backend("exporter", "mine-xyz")
    assert info.loaded and info.plugin == "old" and "old" not in pm.manifests
    assert pm.create("exporter", "mine-xyz", {}).settings == {"digits": 3}


def test_manifest_hooks_module_is_registered_for_workflow_hooks(tmp_path, monkeypatch):
    site = tmp_path / "site"
    events = ("from dotshell import hookimpl\nSEEN = []\n\n@hookimpl\n"
              "def dotshell_view_captured(view):\n    SEEN.append(view)\n")
    _install(site, "hooked_pkg", 'hooks = "hooked_pkg.events"\n', {"__init__": "",
                                                                   "events": events}, ep="hooked")
    monkeypatch.syspath_prepend(str(site))
    pm = PluginManager()
    pm.load_entry_points()
    assert pm.load_errors == [] and "hooked" in pm.manifests
    assert pm.notify("dotshell_view_captured", run_dir="r", view=4, angle_deg=0.0,
                     n_frames=1) == []
    assert sys.modules["hooked_pkg.events"].SEEN == [4]


def test_a_profile_naming_a_broken_backend_fails_with_exit_2_naming_it(my_plugin, tmp_path,
                                                                       capsys):
    raw = small_profile_dict()
    raw["camera"] = {"backend": "mine-cam"}
    code = main(["check", str(write_profile(tmp_path / "p.toml", raw))])
    err = " ".join(capsys.readouterr().err.split())
    assert code == 2 and "Traceback" not in err
    assert "plugin 'mine' (dotshell-mine 1.0) failed to load its camera backend 'mine-cam'" in err
    assert "needs libcam.so" in err and "dotshell plugins --check" in err
