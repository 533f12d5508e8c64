"""The fault matrix: bad input and hostile conditions, each through the real `dotshell` command.

Every case asserts the exit code, that the message names the thing and the fix in one paragraph
with no traceback, and that no file that existed before was changed or lost (the lock, the
appended event log and the manifest's job history excepted; see ``fault_harness.unchanged``).
Runs are made once per module at 0.1 scale (128x102 camera, 2 views) and copied per case with
``cp -a``. The families follow issue 17's list; ``python -m pytest tests/test_faults.py -q
-k profile`` runs one family.
"""

from __future__ import annotations

import errno
import json
import math
import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from conftest import write_profile
from dotshell.cli.app import main
from fault_harness import (Env, FullDisk, counts_are_true, digest_tree, edit_json, frames_on_disk,
                           in_tmpfs, manifest, needs_tmpfs, only_run, replace_file,
                           tiny_profile_dict, unchanged)

NAN, INF = float("nan"), float("inf")


@dataclass
class Case:
    """One fault. ``setup(env)`` returns the command's arguments; the command must exit with
    ``code`` and print every string of ``says`` (``{tmp}`` = the case's directory) on stderr;
    ``then(env, err)`` checks more (the run's state, counts, modes)."""

    family: str
    name: str
    setup: Callable[[Env], list[str]]
    says: tuple[str, ...]
    code: int = 2
    then: Callable[[Env, str], None] | None = None
    state_may_change: bool = False  # a successful job may change the run's status
    marks: tuple = ()

    @property
    def id(self) -> str:
        return f"{self.family}: {self.name}"


CASES: list[Case] = []


def case(family: str, name: str, says: tuple[str, ...], code: int = 2, then=None,
         state_may_change: bool = False, marks: tuple = ()):
    """Decorator: the function is the case's setup."""
    def add(setup: Callable[[Env], list[str]]) -> Callable[[Env], list[str]]:
        CASES.append(Case(family, name, setup, says, code, then, state_may_change, marks))
        return setup
    return add


# ==== shared runs ===============================================================================

def _scan_until(profile: Path, out: Path, stop_at: tuple[int, int] | None) -> Path:
    """A real scan; stopped (as the TUI's abort does) after frame ``stop_at`` = (view, index)."""
    from dotshell.events import EventBus, FrameCaptured
    from dotshell.pipeline.scan import scan
    from dotshell.plugins import PluginManager
    from dotshell.profile.loader import load_profile

    pm = PluginManager()
    pm.load_entry_points()
    stop, bus = threading.Event(), EventBus()
    bus.subscribe(lambda ev: stop.set() if isinstance(ev, FrameCaptured)
                  and (ev.view, ev.index) == stop_at else None)
    result = scan(load_profile(profile, pm), pm, out, bus=bus, stop=stop)
    return result.run_dir


def _make_shared(kind: str, d: Path) -> Path:
    prof = write_profile(d / "p.toml", tiny_profile_dict())
    if kind == "base":  # completed
        run = _scan_until(prof, d / "runs", None)
    elif kind == "aborted":  # view 0 complete, view 1 stopped after 5 of 30 frames
        run = _scan_until(prof, d / "runs", (1, 4))
    elif kind == "empty":  # stopped during view 0: no complete view, nothing published
        run = _scan_until(prof, d / "runs", (0, 2))
    else:
        raise KeyError(kind)
    assert manifest(run)["status"] == ("completed" if kind == "base" else "aborted")
    return run


@pytest.fixture(scope="module")
def installed_plugins():
    """The installed plugins, loaded once for the cases that add none of their own."""
    from dotshell.plugins import PluginManager

    pm = PluginManager()
    pm.load_entry_points()
    return pm


@pytest.fixture(scope="module")
def shared(tmp_path_factory) -> Callable[[str], Path]:
    made: dict[str, Path] = {}

    def get(kind: str) -> Path:
        if kind not in made:
            made[kind] = _make_shared(kind, tmp_path_factory.mktemp(kind))
        return made[kind]

    return get


def pytest_generate_tests(metafunc) -> None:
    """The cases are defined below the test; parametrize once the module is loaded."""
    if "case" in metafunc.fixturenames:
        metafunc.parametrize("case", [pytest.param(c, id=c.id, marks=c.marks) for c in CASES])


def test_fault(case: Case, tmp_path: Path, monkeypatch, shared, installed_plugins,
               capsys) -> None:
    import dotshell.plugins

    env = Env(tmp_path, monkeypatch, shared)
    try:
        args = case.setup(env)
        if not env.plugins:
            monkeypatch.setattr(dotshell.plugins, "_default", installed_plugins)
        before = digest_tree(tmp_path)
        code = main(args)
        out, err = capsys.readouterr()
        after = digest_tree(tmp_path)
    finally:
        for fn in reversed(env.cleanups):
            fn()
    said = " ".join((err if case.code else out + err).split()).lower()  # rich wraps lines
    assert code == case.code, err
    assert "Traceback" not in err, err
    if case.code == 2:  # one paragraph
        assert [ln.startswith("error:") for ln in err.splitlines()].count(True) == 1, err
    for s in case.says:
        s = " ".join(s.replace("{tmp}", str(tmp_path)).split()).lower()
        assert s in said, (s, err)
    lost = unchanged(before, after, case.state_may_change)
    assert not lost, lost
    if case.then is not None:
        case.then(env, err)


def test_the_matrix_covers_every_family_with_100_cases() -> None:
    families = {c.family for c in CASES}
    assert len(CASES) >= 100, len(CASES)
    assert families >= {"profile", "--set", "--out", "memory", "frames", "manifest",
                        "run profile", "calibration", "cloud", "reference", "layout", "plugins",
                        "damaged run", "states", "writers", "orphans", "permissions"}, families


# ==== 1. profile values (dotshell check) =======================================================

def _profile(family: str, name: str, says: tuple[str, ...], **changes) -> None:
    case(family, name, ("p.toml", *says))(lambda env: ["check", str(env.profile(**changes))])


for key, bad in [("scan__exposure_ms", NAN), ("scan__settle_ms", INF),
                 ("processing__roi__radius_mm", NAN), ("processing__roi__z_max_mm", -INF),
                 ("camera__settings__focal_px", INF), ("camera__settings__cx", NAN),
                 ("projector__settings__focal_px", NAN), ("mesh__node_distance_mm", NAN),
                 ("mesh__optics__musp_per_mm", INF), ("validation__radius_mm", NAN),
                 ("stage__settings__scene__radius_mm", INF)]:
    dotted = key.replace("__", ".")
    _profile("profile", f"{bad} {dotted}", (f"[{dotted}] = {bad}", "expected a finite number"),
             **{key: bad})
_profile("profile", "nan in angles_deg", ("[scan.angles_deg[1]] = nan", "finite"),
         scan__angles_deg=[0.0, NAN])
_profile("profile", "inf in camera dist", ("[camera.settings.dist[2]] = inf", "finite"),
         camera__settings__dist=[0.0, 0.0, INF, 0.0, 0.0])
_profile("profile", "nan in optode matrix", ("[mesh.optodes.sources_mm[0][1]] = nan", "finite"),
         mesh__optodes__sources_mm=[[0.0, NAN, 5.0]])
_profile("profile", "nan in projector position",
         ("[projector.settings.position_mm[0]] = nan", "finite"),
         projector__settings__position_mm=[NAN, 0.0, 0.0])
_profile("profile", "string for an integer", ("[scan.views] = 'twelve'", "expected an integer"),
         scan__views="twelve")
_profile("profile", "string for a bool", ("[scan.pdi] = 'yes'", "true or false"), scan__pdi="yes")
_profile("profile", "bool for a number", ("[scan.exposure_ms] = true", "a number"),
         scan__exposure_ms=True)
_profile("profile", "number for a list", ("[scan.angles_deg] = 30", "a list"),
         scan__angles_deg=30)
_profile("profile", "integer out of range", ("[scan.views] = 0", "[1, 3600]"), scan__views=0)
_profile("profile", "huge integer", ("[scan.views] = 1000000000000", "[1, 3600]"),
         scan__views=10**12)
_profile("profile", "not a choice", ("[validation.shape] = 'sphere'", "valid choices", "'cylinder'"),
         validation__shape="sphere")
_profile("profile", "unknown top-level key", ("unknown key [scna]", "valid keys here", "scan"),
         scna={"views": 3})
_profile("profile", "unknown nested key", ("unknown key [scan.view]", "views"), scan__view=3)
_profile("profile", "unknown backend setting", ("unknown key [camera.settings.focal]",
                                                "focal_px"), camera__settings__focal=100.0)
_profile("profile", "unknown backend", ("[camera.backend] = 'sim-cam'", "valid choices",
                                        "'sim-camera'", "dotshell plugins"),
         camera__backend="sim-cam")
_profile("profile", "missing required key", ("missing required key [profile.name]",),
         profile__name=None)
_profile("profile", "a role that is not a table", ("[camera] = 3", "expected a table"), camera=3)
_profile("profile", "export not a table", ("[export.nirfast]", "on its own line"),
         export={"nirfast": 3})
_profile("profile", "transillumination without a light source",
         ("[transillumination] enabled = true needs a [light_source]",),
         transillumination={"enabled": True})
_profile("profile", "calibration file not named", ("[calibration] needs file",),
         calibration={"source": "file"})


@case("profile", "TOML syntax error", ("p.toml", "not valid TOML", "line 2", "fix the syntax"))
def _(env):
    return ["check", str(env.file("p.toml", "[scan]\nviews = = 3\n"))]


@case("profile", "missing profile", ("{tmp}/nope.toml", "does not exist", "other.toml"))
def _(env):
    env.profile("other.toml")
    return ["check", str(env.tmp / "nope.toml")]


@case("profile", "profile is a directory", ("{tmp}/dir.toml", "is a directory"))
def _(env):
    (env.tmp / "dir.toml").mkdir()
    return ["check", str(env.tmp / "dir.toml")]


@case("profile", "profile not UTF-8", ("p.toml", "cannot be read", "utf-8"))
def _(env):
    return ["check", str(env.file("p.toml", b"[profile]\nname = \"\xff\xfe\"\n"))]


@case("profile", "profile's calibration file missing", ("cal.json", "does not exist"))
def _(env):
    p = env.profile(calibration={"source": "file", "file": "cal.json"})
    return ["scan", str(p), "--out", str(env.tmp / "runs")]


# ==== 2. --set ==================================================================================

def _set(name: str, setting: str, says: tuple[str, ...]) -> None:
    case("--set", name, says)(lambda env: ["check", str(env.profile()), "--set", setting])


_set("nan", "scan.exposure_ms=nan", ("[scan.exposure_ms] = nan", "finite"))
_set("-inf", "scan.settle_ms=-inf", ("[scan.settle_ms] = -inf", "finite"))
_set("nan in a list", "scan.angles_deg=[0, nan]", ("[scan.angles_deg[1]] = nan", "finite"))
_set("not KEY=VALUE", "scan.views", ("'scan.views' is not KEY=VALUE", "scan.views=24"))
_set("unknown key", "scan.veiws=3", ("unknown key [scan.veiws]", "views"))
_set("through a value", "scan.views.x=1", ("[views] is not a table",))
_set("wrong type", "scan.views=abc", ("[scan.views] = 'abc'", "an integer"))
_set("a role replaced by a number", "camera=3", ("[camera] = 3", "a table"))
_set("empty key", "=3", ("unknown key []",))


# ==== 3. --out and the file system ==============================================================

@case("--out", "a file", ("afile", "not a directory"))
def _(env):
    env.file("afile", "x")
    return ["scan", str(env.profile()), "--out", str(env.tmp / "afile")]


@case("--out", "under a file", ("afile/runs", "a part of the path is a file"))
def _(env):
    env.file("afile", "x")
    return ["scan", str(env.profile()), "--out", str(env.tmp / "afile" / "runs")]


@case("--out", "not writable", ("/sys/dotshell-runs", "--out"))
def _(env):
    """/sys refuses new directories even to root (chmod would not stop root)."""
    return ["scan", str(env.profile()), "--out", "/sys/dotshell-runs"]


def _full_disk_during_frames(err_no: int):
    def setup(env):
        p = env.profile()
        # room for the run's first files and about 20 frames (26 kB each in a stack), not 60
        FullDisk(env.monkeypatch, env.tmp / "runs", free=700_000, error=err_no)
        return ["scan", str(p), "--out", str(env.tmp / "runs")]
    return setup


def _failed_with_true_counts(env, err):
    run = only_run(env.tmp / "runs")
    m = manifest(run)
    assert m["status"] == "failed" and "could not write frame" in m["reason"], m["reason"]
    counts_are_true(run)
    assert sum(v["frames"] for v in m["views"]) >= 10  # what was written is kept and counted
    assert not list(run.rglob(".*.tmp"))


case("--out", "disk full while writing frames (ENOSPC)",
     ("could not write frame", "no space left on device", "free disk space", "frames already "
      "written are kept"), then=_failed_with_true_counts)(_full_disk_during_frames(errno.ENOSPC))
case("--out", "quota exceeded while writing frames (EDQUOT)",
     ("could not write frame", "quota", "free disk space"),
     then=_failed_with_true_counts)(_full_disk_during_frames(errno.EDQUOT))


@case("--out", "disk full while re-processing", ("cloud.ply", "no space left on device",
                                                 "free disk space"))
def _(env):
    run = env.run()
    FullDisk(env.monkeypatch, run / "gen", free=200_000)  # the views fit, the cloud does not
    return ["reconstruct", str(run)]


@case("--out", "file size limit (EFBIG)", ("file too large", "ulimit -f"))
def _(env):
    """RLIMIT_FSIZE: the kernel refuses to grow any file past 20 kB with EFBIG (SIGXFSZ
    ignored, as a shell's `ulimit -f` leaves it)."""
    import resource
    import signal

    run = env.run()
    old = resource.getrlimit(resource.RLIMIT_FSIZE)
    sig = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, old[1]))

    def restore():
        resource.setrlimit(resource.RLIMIT_FSIZE, old)
        signal.signal(signal.SIGXFSZ, sig)

    env.cleanups.append(restore)
    return ["reconstruct", str(run)]


# ==== 4. memory =================================================================================

@case("memory", "huge camera", ("out of memory", "lower the camera or projector resolution"))
def _(env):
    return ["scan", str(env.profile()), "--out", str(env.tmp / "runs"),
            "--set", "camera.settings.width=1000000", "--set", "camera.settings.height=1000000"]


@case("memory", "huge projector", ("out of memory", "lower the camera or projector resolution"))
def _(env):
    return ["scan", str(env.profile()), "--out", str(env.tmp / "runs"),
            "--set", "projector.settings.width=1000000",
            "--set", "projector.settings.height=1000000"]


# ==== 5. frames from the camera =================================================================

FAULTY_CAMERA = '''
import numpy as np
from dotshell import hookimpl
from dotshell.backends import Backend
from dotshell.settings import Setting
from dotshell_sim.devices import CAMERA_SCHEMA, SimCamera, world_of

FAULTS = {
    "ok": lambda f: f,
    "none": lambda f: None,
    "list": lambda f: f.tolist(),
    "rgb": lambda f: np.dstack([f, f, f]),
    "single channel": lambda f: f[:, :, None],
    "float": lambda f: f.astype(np.float32),
    "int32": lambda f: f.astype(np.int32),
    "short": lambda f: f[:-1],
    "transposed": lambda f: np.ascontiguousarray(f.T),
    "8 bit": lambda f: (f >> 4).astype(np.uint8),
    "over range": lambda f: f | np.uint16(0xF000),
    "empty": lambda f: f[:0, :0],
    "scalar": lambda f: np.uint16(7),
}
SCHEMA = {**CAMERA_SCHEMA, "fault": Setting("str", "ok", choices=tuple(FAULTS)),
          "after": Setting("int", 0, min=0), "raise_in": Setting("str", "")}


class FaultyCamera(SimCamera):
    def __init__(self, settings, world):
        s = dict(settings)
        self.fault, self.after, self.raise_in = s.pop("fault"), s.pop("after"), s.pop("raise_in")
        super().__init__(s, world)
        self.taken = 0

    def connect(self):
        if self.raise_in == "connect":
            raise OSError(16, "Device or resource busy", "/dev/video7")
        super().connect()

    def capture(self):
        frame = super().capture()
        self.taken += 1
        if self.taken <= self.after:
            return frame
        if self.raise_in == "capture":
            raise IndexError("driver bug: buffer 7 of 4")
        return FAULTS[self.fault](frame)


@hookimpl
def dotshell_cameras():
    return [Backend("faulty-camera", lambda settings, context: FaultyCamera(settings,
                    world_of(context)), SCHEMA, "a camera that misbehaves on purpose")]
'''


def _faulty_scan(env: Env, fault: str, after: int = 0, raise_in: str = "", **changes) -> list[str]:
    env.plugin(FAULTY_CAMERA)
    raw = tiny_profile_dict(**changes)
    raw["camera"]["backend"] = "faulty-camera"
    raw["camera"]["settings"].update(fault=fault, after=after, raise_in=raise_in)
    return ["scan", str(env.profile(raw=raw)), "--out", str(env.tmp / "runs")]


def _frames_refused(first_bad: int):
    def then(env, err):
        run = only_run(env.tmp / "runs")
        m = manifest(run)
        assert m["status"] == "failed", m["status"]
        counts_are_true(run)
        assert sum(v["frames"] for v in m["views"]) == first_bad
    return then


for fault, says in [
    ("none", ("is a NoneType, not an image",)),
    ("list", ("is a list, not an image",)),
    ("scalar", ("is a uint16, not an image",)),
    ("rgb", ("is a colour image (3 channels)", "monochrome")),
    ("float", ("is float32", "uint8 or uint16")),
    ("int32", ("is int32", "uint8 or uint16")),
    ("short", ("is 128x101 px", "camera's resolution is 128x102 px")),
    ("transposed", ("is 102x128 px", "128x102 px")),
    ("empty", ("is 0x0 px",)),
    ("8 bit", ("is uint8 (8 bit)", "reports 12 bit", "bit_depth")),
    ("over range", ("values up to", "12 bit (0..4095)")),
]:
    case("frames", f"camera returns {fault}",
         ("view 0, frame 'white'", "faulty-camera", *says), then=_frames_refused(0))(
        lambda env, fault=fault: _faulty_scan(env, fault))

case("frames", "an 8-bit frame in the middle of a 12-bit view",
     ("view 0, frame 'col_05'", "is uint8 (8 bit)", "reports 12 bit"),
     then=_frames_refused(12))(lambda env: _faulty_scan(env, "8 bit", after=12))
case("frames", "an 8-bit frame in the second view",
     ("view 1, frame 'white'", "is uint8 (8 bit)"),
     then=_frames_refused(30))(lambda env: _faulty_scan(env, "8 bit", after=30))


@case("frames", "single-channel 3-D frames are taken as 2-D", (), code=0)
def _(env):
    return _faulty_scan(env, "single channel")


@case("frames", "an 8-bit trans-illumination (flat-field) frame in a 12-bit run",
      ("flat-field frame 'flat'", "is uint8 (8 bit)", "reports 12 bit"))
def _(env):
    return _faulty_scan(env, "8 bit", light_source={"backend": "sim-laser"},
                        transillumination={"enabled": True, "views": [0],
                                           "targets_mm": [[0.0, 10.0]]})


@case("frames", "calibration for another camera size", ("128x102", "256x204", "calibration"))
def _(env):
    from dotshell.geometry.calibration import RigCalibration
    from dotshell.geometry.lens import lens_from_fov

    cal = RigCalibration.load(env.shared("base") / "calibration.json")
    big = RigCalibration(lens_from_fov(256, 204, cal.camera.K[0, 0] * 2), cal.projector, cal.R,
                         cal.T, cal.axis_point, cal.axis_direction, "big")
    big.save(env.tmp / "big.json")
    return ["scan", str(env.profile()), "--out", str(env.tmp / "runs"), "--calibration",
            str(env.tmp / "big.json")]


# ==== 6. the manifest ===========================================================================

def _manifest_case(name: str, change, says: tuple[str, ...], command: str = "reconstruct"):
    def setup(env):
        run = env.run()
        edit_json(run / "manifest.json", change)
        return [command, str(run)]
    case("manifest", f"{name} ({command})", ("manifest.json", *says))(setup)


def _set_key(key, value):
    def change(m):
        m[key] = value
        return m
    return change


def _view_key(key, value, view=0):
    def change(m):
        m["views"][view][key] = value
        return m
    return change


_manifest_case("a list", lambda m: [m], ("holds a list, not an object", "restore it"))
_manifest_case("no status", lambda m: {k: v for k, v in m.items() if k != "status"},
               ("'status' is missing",), command="inspect")
_manifest_case("views not a list", _set_key("views", {"0": 1}), ("'views' is missing or not a list",))
_manifest_case("view index wrong", _view_key("index", 5), ("views[0] has index 5",))
_manifest_case("angle NaN", _view_key("angle_deg", NAN), ("views[0] has index 0 / angle nan",),
               command="resume")
_manifest_case("frames a string", _view_key("frames", "30"), ("views[0].frames",))
_manifest_case("complete a string", _view_key("complete", "yes"), ("views[0].complete",),
               command="mesh")
_manifest_case("frame name empty", _set_key("frame_names", ["white", ""]),
               ("frame_names must be non-empty strings",))
_manifest_case("frames counted beyond the sequence", _view_key("frames", 99),
               ("views[0] counts 99 frames", "30"))
_manifest_case("negative frame count", _view_key("frames", -1), ("views[0] counts -1 frames",))
_manifest_case("truncated JSON", lambda m: json.dumps(m)[:200], ("not valid JSON",),
               command="inspect")
_manifest_case("empty file", lambda m: "", ("not valid JSON",), command="resume")
_manifest_case("trans-illumination entry not an object", _set_key("transillumination", [1]),
               ("'transillumination' is not an object",))
_manifest_case("trans-illumination exposure NaN",
               _set_key("transillumination", {"exposure_ms": NAN, "camera_bit_depth": 12,
                                              "targets_mm": [None], "frame_names": ["src_00"],
                                              "flat_field": None, "views": {}}),
               ("transillumination.exposure_ms",))
_manifest_case("camera bit depth 40", _set_key("camera", {"width": 128, "height": 102,
                                                          "bit_depth": 40}),
               ("camera.bit_depth",))


@case("manifest", "missing manifest", ("is not a dotshell run directory", "no manifest.json"))
def _(env):
    run = env.run()
    (run / "manifest.json").unlink()
    return ["reconstruct", str(run)]


@case("manifest", "manifest is a directory", ("manifest.json",))
def _(env):
    run = env.run()
    (run / "manifest.json").unlink()
    (run / "manifest.json").mkdir()
    return ["inspect", str(run)]


# ==== 7. the run's profile (TOML errors in a run) ===============================================

def _run_profile(name: str, content, says: tuple[str, ...], command: str = "reconstruct",
                 kind: str = "base") -> None:
    """``content``: the new profile.toml (bytes), None (deleted) or a change of its text."""
    def setup(env):
        run = env.run(kind)
        if content is None:
            (run / "profile.toml").unlink()
        elif callable(content):
            text = (run / "profile.toml").read_text()
            assert content(text) != text
            replace_file(run / "profile.toml", content(text))
        else:
            replace_file(run / "profile.toml", content)
        return [command, str(run)]
    case("run profile", f"{name} ({command})", ("profile.toml", *says))(setup)


_run_profile("syntax error", b"[scan\nviews = 3\n", ("is damaged", "restore it"))
_run_profile("syntax error", b"[scan\nviews = 3\n", ("is damaged",), command="resume",
             kind="aborted")
_run_profile("missing", None, ("is missing", "cannot be re-processed"))
_run_profile("not UTF-8", b"[profile]\nname = \"\xff\"\n", ("is damaged",), command="mesh")
_run_profile("NaN value", lambda t: t.replace("exposure_ms = 20.0", "exposure_ms = nan"),
             ("[scan.exposure_ms] = nan", "finite"))
_run_profile("unknown key", lambda t: t.replace("[scan]\n", "[scan]\nveiws = 3\n"),
             ("unknown key [scan.veiws]", "views"))


@case("run profile", "its plugin was uninstalled", ("'gone-camera'", "not an installed camera",
                                                    "sim-camera"))
def _(env):
    run = env.run()
    text = (run / "profile.toml").read_text().replace('"sim-camera"', '"gone-camera"', 1)
    replace_file(run / "profile.toml", text)
    return ["reconstruct", str(run)]


# ==== 8. calibration files ======================================================================

def _good_calibration(env: Env) -> dict:
    return json.loads((env.shared("base") / "calibration.json").read_text())


def _calibration_case(name: str, make, says: tuple[str, ...], command: str = "reconstruct"):
    def setup(env):
        content = make(_good_calibration(env))
        f = env.file("cal.json", content)
        if command == "scan":
            return ["scan", str(env.profile()), "--out", str(env.tmp / "runs"),
                    "--calibration", str(f)]
        return ["reconstruct", str(env.run()), "--calibration", str(f)]
    case("calibration", f"{name} ({command})", ("{tmp}/cal.json", *says))(setup)


def _with(**changes):
    def make(good):
        out = dict(good)
        for dotted, v in changes.items():
            *path, key = dotted.split("__")
            d = out
            for p in path:
                d[p] = dict(d[p])
                d = d[p]
            d[key] = v
        return out
    return make


_calibration_case("a list", lambda g: [1, 2, 3], ("a json object, not a list",
                                                  "dotshell calibrate"))
_calibration_case("a list", lambda g: [1, 2, 3], ("a json object, not a list",), command="scan")
_calibration_case("NaN in T", _with(T=[NAN, 0, 0]), ("nan or infinity", "re-solve it"))
_calibration_case("inf in the camera matrix",
                  _with(camera__K=[[INF, 0, 64], [0, 100, 51], [0, 0, 1]]),
                  ("camera matrix or distortion holds nan or infinity",), command="scan")
_calibration_case("singular R", _with(R=[[1, 0, 0], [0, 0, 0], [0, 0, 1]]),
                  ("r is not a rotation matrix",))
_calibration_case("zero baseline", _with(T=[0, 0, 0]), ("no baseline",))
_calibration_case("zero axis direction", _with(turntable__axis_direction=[0, 0, 0]),
                  ("zero axis direction",))
_calibration_case("negative focal length", _with(camera__K=[[-100, 0, 64], [0, 100, 51], [0, 0, 1]]),
                  ("non-positive focal length",))
_calibration_case("2x2 camera matrix", _with(camera__K=[[1, 0], [0, 1]]),
                  ("incomplete or malformed", "needs camera, projector"))
_calibration_case("width not a number", _with(camera__width="wide"),
                  ("incomplete or malformed",))
_calibration_case("missing the turntable", lambda g: {k: v for k, v in g.items()
                                                      if k != "turntable"},
                  ("incomplete or malformed", "turntable"))
_calibration_case("another format", _with(format="opencv/1"),
                  ("not a dotshell calibration", "dotshell-calibration/1"))
_calibration_case("another camera size", _with(camera__width=256),
                  ("its camera is 256x102 px", "frames are 128x102 px"))
_calibration_case("not JSON", lambda g: "{not json", ("is not valid JSON",))
_calibration_case("empty", lambda g: "", ("is not valid JSON",), command="scan")
_calibration_case("not UTF-8", lambda g: b"\xff\xfe{}", ("is not valid JSON",))


# ==== 8b. calibration models and sizes (issue 33) ===============================================

_calibration_case("40 distortion terms", _with(camera__dist=[0.01] * 40),
                  ("40 distortion terms", "4, 5, 8, 12 or 14", "k4, k5, k6, s1"))
_calibration_case("tilted sensor terms", _with(projector__dist=[0.0] * 12 + [0.02, 0.0]),
                  ("tilted-sensor distortion", "tau_x = 0.02"))
_calibration_case("width 128.5", _with(camera__width=128.5),
                  ("width 128.5 is not a whole number of pixels",))


@case("calibration model", "/dev/zero as the calibration",
      ("/dev/zero is not a regular file", "calibration.json"))
def _(env):
    return ["reconstruct", str(env.run()), "--calibration", "/dev/zero"]


def _reconstructed_with_the_yml(env: Env, err: str) -> None:
    run = env.tmp / "run1"
    assert manifest(run)["status"] == "completed"
    gens = sorted((run / "gen").iterdir())
    assert any(str(env.tmp / "cal.yml") in (g / "calibration.json").read_text()
               for g in gens if (g / "calibration.json").exists()), gens


@case("calibration model", "an OpenCV .yml for a run (reconstruct RUN --calibration)", (),
      code=0, then=_reconstructed_with_the_yml, state_may_change=True)
def _(env):
    from dotshell.geometry.calibration import RigCalibration
    from dotshell.geometry.opencv_io import write_opencv_calibration

    run = env.run()
    calib = RigCalibration.load(run / "calibration.json")
    write_opencv_calibration(calib, env.tmp / "cal.yml")
    return ["reconstruct", str(run), "--calibration", str(env.tmp / "cal.yml")]


@case("calibration", "a directory", ("{tmp}/caldir", "is a directory, not a file"))
def _(env):
    (env.tmp / "caldir").mkdir()
    return ["reconstruct", str(env.run()), "--calibration", str(env.tmp / "caldir")]


@case("calibration", "the run's own calibration damaged (resume)",
      ("calibration.json", "not valid JSON", "dotshell calibrate"))
def _(env):
    run = env.run("aborted")
    replace_file(run / "calibration.json", "{")
    return ["resume", str(run)]


@case("calibration", "the run's own calibration NaN (resume)",
      ("calibration.json", "nan or infinity"))
def _(env):
    run = env.run("aborted")
    edit_json(run / "calibration.json", _with(T=[NAN, 0.0, 0.0]))
    return ["resume", str(run)]


@case("calibration", "without a measured turntable axis (scan)",
      ("no measured turntable axis", "dotshell calibrate", "scan.views=1"))
def _(env):
    from dotshell.plugins import PluginManager
    from dotshell.profile.loader import load_profile
    from dotshell.rig.assembly import Rig

    prof = env.profile()
    pm = PluginManager()
    pm.load_entry_points()
    calib = Rig(load_profile(prof, pm), pm).calibration().to_dict()
    calib["turntable"]["measured"] = False
    f = env.file("cal.json", calib)
    return ["scan", str(prof), "--out", str(env.tmp / "runs"), "--calibration", str(f)]


@case("profile", "every point outside the region of interest",
      ("no pixel decoded into a point", "lost to ray_outside_roi",
       "the camera ray misses [processing.roi]", "radius_mm, z_min_mm, z_max_mm"))
def _(env):
    return ["scan", str(env.profile(processing__roi__radius_mm=0.01)), "--out",
            str(env.tmp / "runs")]


@case("profile", "a region of interest the rays cross where the sample is not",
      ("were triangulated but no point is left", "outside the region of interest",
       "[processing.roi]"))
def _(env):  # above the 30 mm cylinder: the rays cross it on their way to the background
    return ["scan", str(env.profile(processing__roi__z_min_mm=32.0,
                                    processing__roi__z_max_mm=36.0)),
            "--out", str(env.tmp / "runs")]


@case("calibration", "broken OpenCV .yml", ("{tmp}/cal.yml", "not a readable opencv"))
def _(env):
    f = env.file("cal.yml", "%YAML:1.0\n---\nK: !!opencv-matrix\n  rows: 3\n  cols: [\n")
    return ["reconstruct", "--captures", str(env.tmp), "--calibration", str(f), "--layout",
            "opencv-graycode", "--out", str(env.tmp / "out")]


@case("calibration", "OpenCV .xml without the camera matrix", ("{tmp}/cal.xml", "has no"))
def _(env):
    f = env.file("cal.xml", '<?xml version="1.0"?>\n<opencv_storage>\n<Rc>1</Rc>\n'
                 "</opencv_storage>\n")
    return ["reconstruct", "--captures", str(env.tmp), "--calibration", str(f), "--layout",
            "opencv-graycode", "--out", str(env.tmp / "out")]


# ==== 9. point clouds ===========================================================================

def _cloud_bytes(env: Env) -> bytes:
    return (env.shared("base") / "cloud.ply").read_bytes()


def _cloud_case(name: str, damage, says: tuple[str, ...], command: str = "mesh") -> None:
    def setup(env):
        run = env.run()
        replace_file(run / "cloud.ply", damage(_cloud_bytes(env)))
        if command == "validate":
            return ["validate", str(run), "--out", str(env.tmp / "val")]
        return [command, str(run)]
    case("cloud", f"{name} ({command})", ("cloud.ply", *says))(setup)


def _header(data: bytes) -> tuple[bytes, bytes]:
    end = data.index(b"end_header\n") + len(b"end_header\n")
    return data[:end], data[end:]


def _swap_header(old: bytes, new: bytes):
    def damage(data):
        head, body = _header(data)
        return head.replace(old, new) + body
    return damage


_cloud_case("empty file", lambda d: b"", ("is not a PLY file",))
_cloud_case("no end_header", lambda d: _header(d)[0][:-11] + _header(d)[1],
            ("is not a PLY file",), command="validate")
_cloud_case("no vertex element", _swap_header(b"element vertex", b"element points"),
            ("no vertex element", "points"))
_cloud_case("vertex count not a number", _swap_header(b"element vertex ", b"element vertex x"),
            ("header line", "element vertex x", "integer count"))
_cloud_case("vertex count beyond the data", lambda d: _swap_header(
    b"element vertex ", b"element vertex 9")(d), ("data ends after", "vertices its header declares"))
_cloud_case("truncated data", lambda d: d[: len(d) // 2], ("data ends after", "cut short"),
            command="validate")
_cloud_case("no x property", _swap_header(b"property float x", b"property float q"),
            ("need x, y, z",))
_cloud_case("double properties", _swap_header(b"property float x", b"property double x"),
            ("data ends after", "property types (double x, float y"))
_cloud_case("ascii format", _swap_header(b"binary_little_endian", b"ascii"),
            ("format ascii", "not the text"))
_cloud_case("non-ASCII header", _swap_header(b"comment dotshell", b"comment \xff\xfe"),
            ("header is not ascii",))
_cloud_case("NaN points", lambda d: _header(d)[0] + np.full(len(_header(d)[1]) // 4, np.nan,
                                                            "<f4").tobytes(),
            ("non-finite",))


@case("cloud", "a view's cloud damaged when re-merging",
      ("view_000.ply", "is not a PLY file"))
def _(env):
    """`dotshell reconstruct` makes the views again; a view cloud damaged in the current
    generation is met by a job that carries the views over: here the mesh step never starts
    because merging needs them (the cloud is rebuilt when only views exist)."""
    run = env.run()
    replace_file(run / "current" / "views" / "view_000.ply", b"garbage")
    products = run / "current" / "products.json"
    edit_json(products, lambda p: {**p, "files": {k: v for k, v in p["files"].items()
                                                  if k != "cloud"}})
    (run / "current" / "cloud.ply").unlink()
    return ["mesh", str(run)]


# ==== 10. a reference cloud and layouts (captures made elsewhere) ================================

def _captures(env: Env) -> tuple[Path, Path]:
    """View 0 of the base run as a foreign capture folder, and a layout for it."""
    run = env.shared("base")
    d = env.tmp / "caps"
    d.mkdir(exist_ok=True)
    for i, f in enumerate(sorted((run / "frames" / "view_000").glob("*.png"))):
        (d / f"f_{i:03d}.png").write_bytes(f.read_bytes())
    cal = json.loads((run / "calibration.json").read_text())
    layout = env.file("layout.toml", (
        "[layout]\nname = \"own\"\nfiles = \"f_{index:03d}.png\"\n"
        f"projector_width = {cal['projector']['width']}\n"
        f"projector_height = {cal['projector']['height']}\n"
        "order = [\"white\", \"black\", \"columns\", \"rows\"]\ninverse = true\ncentred = true\n"))
    return d, layout


def _captures_args(env: Env, layout: Path | None = None, **extra: str) -> list[str]:
    d, own = _captures(env)
    args = ["reconstruct", "--captures", str(d), "--calibration",
            str(env.shared("base") / "calibration.json"), "--layout", str(layout or own),
            "--out", str(env.tmp / "out")]
    for k, v in extra.items():
        args += [f"--{k}", v]
    return args


def _nothing_written(env, err):
    out = env.tmp / "out"
    assert not out.exists() or not any(out.iterdir()), list(out.iterdir())


@case("reference", "a one-point reference", ("one.ply", "1 point", "at least 12"),
      then=_nothing_written)
def _(env):
    from dotshell.run.ply import write_ply

    write_ply(env.tmp / "one.ply", np.array([[0.0, 0.0, 200.0]]))
    return _captures_args(env, reference=str(env.tmp / "one.ply"))


@case("reference", "a damaged reference", ("ref.ply", "is not a PLY file"), then=_nothing_written)
def _(env):
    env.file("ref.ply", b"plx\n")
    return _captures_args(env, reference=str(env.tmp / "ref.ply"))


@case("reference", "a missing reference", ("nope.ply", "does not exist"), then=_nothing_written)
def _(env):
    return _captures_args(env, reference=str(env.tmp / "nope.ply"))


def _layout_case(name: str, files: str, says: tuple[str, ...]) -> None:
    def setup(env):
        d, own = _captures(env)
        bad = env.file("bad.toml", own.read_text().replace('"f_{index:03d}.png"', repr(files)))
        return _captures_args(env, layout=bad)
    case("layout", name, ("bad.toml", "[layout] files", *says), then=_nothing_written)(setup)


_layout_case("a positional field {0}", "f_{index:03d}_{0}.png", ("{0}", "only {index}"))
_layout_case("an unknown field {other}", "f_{index:03d}_{other}.png", ("{other}", "only {index}"))
_layout_case("a bad format spec", "f_{index:q}.png", ("{index:q}",))
_layout_case("an unclosed brace", "f_{index.png", ("f_{index.png",))


# ==== 10b. captures of mixed pixel formats (issue 33) ===========================================

def _mixed_captures(env: Env, convert) -> list[str]:
    """The captures (16-bit) with frame 5 converted by ``convert`` (an 8-bit or a colour frame):
    such a mix was decoded with exit 0 (issue 33: 1,920 of 3,840 pixels off by up to 31
    projector columns)."""
    import cv2

    from dotshell.run.frames import export_png, open_frames

    run = env.shared("base")
    (env.tmp / "caps").mkdir()
    for i, p in enumerate(export_png(open_frames(run, 0, manifest(run)), env.tmp / "png")):
        p.rename(env.tmp / "caps" / f"f_{i:03d}.png")
    args = _captures_args(env)
    f = env.tmp / "caps" / "f_005.png"
    cv2.imwrite(str(f), convert(cv2.imread(str(f), cv2.IMREAD_UNCHANGED)))
    return args


case("captures", "one 8-bit frame among 16-bit frames",
     ("f_005.png (uint8, 1 channel)", "f_000.png is uint16, 1 channel", "one pixel format"),
     then=_nothing_written)(lambda env: _mixed_captures(env, lambda im: (im >> 4).astype(np.uint8)))
case("captures", "one colour frame among grey frames",
     ("f_005.png (uint16, 3 channels)", "differ in bit depth or channels"),
     then=_nothing_written)(lambda env: _mixed_captures(env, lambda im: np.dstack([im] * 3)))


# ==== 11. plugins ===============================================================================

def _backend_plugin(hook: str, body: str) -> str:
    return ("from dotshell import hookimpl\nfrom dotshell.backends import Backend\n"
            "from dotshell.settings import Setting\n"
            f"{body}\n@hookimpl\ndef {hook}():\n    return BACKENDS\n")


def _plugin_scan(env: Env, source: str, role: str | None = None, backend: str = "",
                 **changes) -> list[str]:
    env.plugin(source)
    raw = tiny_profile_dict(**changes)
    if role:
        raw[role] = {"backend": backend}
    return ["scan", str(env.profile(raw=raw)), "--out", str(env.tmp / "runs")]


@case("plugins", "a factory raising", ("plugin 'faulty'", "role stage", "'boom-stage'",
                                       "zerodivisionerror", "fault of the plugin"))
def _(env):
    return _plugin_scan(env, _backend_plugin("dotshell_stages", (
        "def boom(settings, context):\n    raise ZeroDivisionError('driver bug')\n"
        "BACKENDS = [Backend('boom-stage', boom)]")), "stage", "boom-stage")


@case("plugins", "a factory running out of memory", ("out of memory",))
def _(env):
    return _plugin_scan(env, _backend_plugin("dotshell_stages", (
        "def boom(settings, context):\n    raise MemoryError()\n"
        "BACKENDS = [Backend('greedy-stage', boom)]")), "stage", "greedy-stage")


@case("plugins", "a factory returning None", ("'none-stage'", "role stage", "lacks", "connect"))
def _(env):
    return _plugin_scan(env, _backend_plugin("dotshell_stages", (
        "BACKENDS = [Backend('none-stage', lambda settings, context: None)]")),
        "stage", "none-stage")


@case("plugins", "connect raising a plain exception",
      ("plugin 'faulty'", "role camera", "faulty-camera", "connect", "device or resource busy"),)
def _(env):
    return _faulty_scan(env, "ok", raise_in="connect")


@case("plugins", "capture raising a plain exception",
      ("plugin 'faulty'", "role camera", "faulty-camera", "capture", "driver bug"),
      then=_frames_refused(3),)
def _(env):
    return _faulty_scan(env, "ok", after=3, raise_in="capture")


def _load_error(name: str, source: str, says: tuple[str, ...], command: str = "plugins") -> None:
    code = 1 if command == "plugins" else 0

    def setup(env):
        env.plugin(source)
        return ["plugins"] if command == "plugins" else ["check", str(env.profile())]
    case("plugins", f"{name} ({command})", ("plugin 'faulty'", *says), code=code)(setup)


_load_error("a backend hook returning a string",
            _backend_plugin("dotshell_stages", "BACKENDS = 'not a list'"),
            ("must return a list of dotshell.backends.backend", "'not a list'"))
_load_error("a backend hook returning the wrong type",
            _backend_plugin("dotshell_cameras", "BACKENDS = [42]"), ("[42]",), command="check")
_load_error("a broken settings schema",
            _backend_plugin("dotshell_stages", "BACKENDS = [Backend('x', lambda **k: 1, "
                            "{'speed': 3})]"), ("settings schema",))
_load_error("an invalid setting kind at import",
            _backend_plugin("dotshell_stages", "BACKENDS = [Backend('x', lambda **k: 1, "
                            "{'speed': Setting('float64')})]"), ("unknown setting kind",))
_load_error("a backend hook raising",
            "from dotshell import hookimpl\n@hookimpl\ndef dotshell_codings():\n"
            "    raise RuntimeError('cannot find libcode')\n", ("libcode",), command="check")
_load_error("sys.exit at import", "import sys\nsys.exit(3)\n", ("systemexit: 3",),
            command="check")
_load_error("a duplicate of a first-party backend",
            _backend_plugin("dotshell_cameras", "BACKENDS = [Backend('sim-camera', "
                            "lambda settings, context: None)]"),
            ("already provided by plugin 'sim'", "faulty:sim-camera"), command="check")


def _manifest_scan(env: Env, role: str, body: str) -> list[str]:
    """A scan whose ``role`` is backend ``m-dev`` of a manifest plugin, its module ``body``."""
    env.manifest_plugin(f'[[backends]]\nkind = "{role}"\nname = "m-dev"\nsummary = "s"\n'
                        'python_name = "PKG.driver:BACKEND"\n', {"driver": body})
    raw = tiny_profile_dict()
    raw[role] = {"backend": "m-dev"}
    return ["scan", str(env.profile(raw=raw)), "--out", str(env.tmp / "runs")]


@case("plugins", "a manifest backend whose module fails to import",
      ("plugin 'faulty'", "failed to load its stage backend 'm-dev'", "needs libstage.so",
       "dotshell plugins --check"))
def _(env):
    return _manifest_scan(env, "stage", "raise ImportError('needs libstage.so')\n")


@case("plugins", "a manifest python_name that is not a Backend",
      ("plugin 'faulty'", "'m-dev'", "must be (or return) a dotshell.backends.backend"))
def _(env):
    return _manifest_scan(env, "stage", "BACKEND = 42\n")


@case("plugins", "a manifest backend of another name",
      ("'m-dev'", "named 'm-dev', as the manifest says", "other-name"))
def _(env):
    return _manifest_scan(env, "stage", "from dotshell.backends import Backend\n"
                          "BACKEND = Backend('other-name', lambda **k: None)\n")


@case("plugins", "a manifest of an unknown kind (plugins)",
      ("plugin 'faulty'", "dotshell.toml: [[backends]] #1", "kind = 'turntable' is not a role"),
      code=1)
def _(env):
    env.manifest_plugin('[[backends]]\nkind = "turntable"\nname = "t"\n'
                        'python_name = "PKG.t:B"\n', {})
    return ["plugins"]


@case("plugins", "a manifest that is not TOML (plugins)",
      ("plugin 'faulty'", "is not a readable toml manifest"), code=1)
def _(env):
    env.manifest_plugin('[[backends]\nkind = \n', {})
    return ["plugins"]


@case("plugins", "a workflow hook raising", ("plugin 'faulty'", "dotshell_view_captured",
                                             "went on without it"), code=0)
def _(env):
    return _plugin_scan(env, "from dotshell import hookimpl\n@hookimpl\n"
                        "def dotshell_view_captured(view):\n    raise KeyError('observer')\n")


@case("plugins", "a workflow hook hanging", ("plugin 'faulty'", "did not return within 0.2 s"),
      code=0)
def _(env):
    import dotshell.plugins

    env.monkeypatch.setattr(dotshell.plugins, "HOOK_TIMEOUT_S", 0.2)
    return _plugin_scan(env, "import time\nfrom dotshell import hookimpl\n@hookimpl\n"
                        "def dotshell_scan_started(run_dir):\n    time.sleep(3)\n")


@case("plugins", "an exporter raising", ("plugin 'faulty'", "role exporter", "'bad-export'",
                                         "export()", "disk on fire"))
def _(env):
    return _plugin_scan(env, _backend_plugin("dotshell_exporters", (
        "class Bad:\n    def export(self, run_dir):\n        raise ValueError('disk on fire')\n"
        "BACKENDS = [Backend('bad-export', lambda settings, context: Bad())]")),
        export={"bad-export": {}})


@case("plugins", "a coding raising", ("plugin 'faulty'", "role coding", "'bad-code'", "patterns"))
def _(env):
    return _plugin_scan(env, _backend_plugin("dotshell_codings", (
        "class Bad:\n    def patterns(self, resolution):\n        return 1 / 0\n"
        "BACKENDS = [Backend('bad-code', lambda settings, context: Bad())]")),
        "coding", "bad-code")


# ==== 12. re-processing damaged runs ============================================================

def _damaged(name: str, damage, says: tuple[str, ...], command: str = "reconstruct",
             code: int = 2, then=None) -> None:
    def setup(env):
        run = env.run()
        damage(run)
        return [command, str(run)]
    case("damaged run", f"{name} ({command})", says, code=code, then=then)(setup)


def _the_run(env: Env) -> Path:
    return next(p for p in sorted(env.tmp.iterdir()) if p.name.startswith("run"))


def _published(env: Env, generation: str) -> None:
    run = _the_run(env)
    assert (run / "current").resolve().name == generation
    assert (run / "cloud.ply").is_file()


def _as_png_run(run: Path) -> Path:
    """The run as one made before frame stacks: each view's frames as PNG files and the
    manifest without ``frame_format`` (what old runs on disk look like)."""
    import json

    from dotshell.run.frames import export_png
    from dotshell.run.store import RunStore

    store = RunStore.open(run)
    for v in store.manifest["views"]:
        stack = store.frames(v["index"])
        export_png(stack, run / "frames")
        stack.path.unlink()
    m = json.loads((run / "manifest.json").read_text())
    m.pop("frame_format")
    replace_file(run / "manifest.json", json.dumps(m))
    return run


def _frame(run: Path, index: int = 3, view: int = 0) -> Path:
    return sorted((run / "frames" / f"view_{view:03d}").glob("*.png"))[index]


def _write_png(path: Path, image: np.ndarray) -> None:
    import cv2

    replace_file(path, cv2.imencode(".png", image)[1].tobytes())


def _stack(run: Path, view: int = 0) -> Path:
    return run / "frames" / f"view_{view:03d}.tif"


def _rewrite_stack(run: Path, change) -> None:
    """Write the view's stack again with ``change(pages, names)`` applied (lists of arrays and
    page names), as another program writing TIFF would."""
    import tifffile

    with tifffile.TiffFile(_stack(run)) as tif:
        pages = [p.asarray() for p in tif.pages]
        names = [p.description for p in tif.pages]
    change(pages, names)
    with tifffile.TiffWriter(_stack(run)) as out:
        for page, name in zip(pages, names):
            out.write(page, description=name, metadata=None)


def _set(i: int, value):
    def change(pages, names):
        pages[i] = value
    return change


_damaged("a PNG frame deleted (a run before stacks)",
         lambda r: _frame(_as_png_run(r)).unlink(),
         ("003_col_00_inv.png", "is missing or unreadable", "cannot be reconstructed"))
_damaged("a PNG frame truncated (a run before stacks)",
         lambda r: replace_file(_frame(_as_png_run(r)), _frame(r).read_bytes()[:100]),
         ("003_col_00_inv.png", "is missing or unreadable"))
_damaged("a PNG frame of another size (a run before stacks)",
         lambda r: _write_png(_frame(_as_png_run(r)), np.zeros((50, 60), np.uint16)),
         ("003_col_00_inv.png", "is 60x50 px", "128x102"))
_damaged("an RGB PNG frame (a run before stacks)",
         lambda r: _write_png(_frame(_as_png_run(r)), np.zeros((102, 128, 3), np.uint8)),
         ("003_col_00_inv.png", "colour image"))
_damaged("an 8-bit PNG frame in a 12-bit run (a run before stacks)",
         lambda r: _write_png(_frame(_as_png_run(r)), np.zeros((102, 128), np.uint8)),
         ("003_col_00_inv.png", "is uint8 (8 bit)", "12 bit"))
_damaged("a view's frame stack deleted", lambda r: _stack(r).unlink(),
         ("view_000.tif", "missing", "cannot be reconstructed"))
_damaged("a frame stack cut short mid-page",
         lambda r: replace_file(_stack(r), _stack(r).read_bytes()[:_stack(r).stat().st_size // 2]),
         ("view_000.tif", "frames"))
_damaged("a frame stack that is not a TIFF", lambda r: replace_file(_stack(r), b"not a tiff"),
         ("view_000.tif",))
_damaged("a page of another size in the stack",
         lambda r: _rewrite_stack(r, _set(3, np.zeros((50, 60), np.uint16))),
         ("col_00_inv", "is 60x50 px", "128x102"))
_damaged("an 8-bit page in a 12-bit stack",
         lambda r: _rewrite_stack(r, _set(3, np.zeros((102, 128), np.uint8))),
         ("col_00_inv", "8 bit", "12 bit"))
_damaged("an RGB page in the stack",
         lambda r: _rewrite_stack(r, _set(3, np.zeros((102, 128, 3), np.uint8))),
         ("view_000.tif", "page 3", "single-channel"))
_damaged("pages of the stack in another order",
         lambda r: _rewrite_stack(r, lambda pages, names: names.reverse()),
         ("view_000.tif", "does not belong to this run"))
_damaged("frames directory gone", lambda r: __import__("shutil").rmtree(r / "frames"),
         ("view_000.tif", "is missing"))
_damaged("products.json damaged", lambda r: replace_file(r / "current" / "products.json", "{"),
         ("products.json is damaged", "dotshell reconstruct"), command="mesh")
_damaged("products.json a list", lambda r: replace_file(r / "current" / "products.json", "[]"),
         ("products.json is damaged",), command="mesh")
_damaged("report.json damaged", lambda r: replace_file(r / "current" / "report.json", "{x"),
         ("report.json is not valid json", "dotshell reconstruct"), command="mesh")
_damaged("generation directory gone (products re-made from the frames)",
         lambda r: __import__("shutil").rmtree(r / "gen" / "001"), ("gen/001", "missing"),
         code=0, then=lambda env, err: _published(env, "001"))
_damaged("current is a directory (copied without -a)",
         lambda r: (os.unlink(r / "current"), (r / "current").mkdir()),
         ("is a directory, not a symbolic link", "cp -a"), command="mesh")
_damaged("the generation's calibration damaged",
         lambda r: replace_file(r / "current" / "calibration.json", "[]"),
         ("calibration.json", "a json object, not a list", "dotshell calibrate"))


def _cube_vtu() -> bytes:
    """A 10 mm cube of five tetrahedra with optical properties, as volume.vtu bytes."""
    import tempfile

    import meshio

    nodes = 10.0 * np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1],
                             [1, 1, 1], [0, 1, 1]], float)
    tets = np.array([[0, 1, 3, 4], [1, 2, 3, 6], [1, 4, 5, 6], [3, 4, 6, 7], [1, 3, 4, 6]])
    data = {"mua_per_mm": np.full(8, 0.01), "musp_per_mm": np.full(8, 1.0),
            "refractive_index": np.full(8, 1.33), "boundary": np.ones(8, np.int32)}
    with tempfile.TemporaryDirectory() as d:
        meshio.write(f"{d}/v.vtu", meshio.Mesh(nodes, [("tetra", tets)], point_data=data))
        return Path(f"{d}/v.vtu").read_bytes()


def _add_mesh(run: Path, files: dict[str, bytes]) -> None:
    """Give the current generation mesh products (the files under test)."""
    cur = run / "current"
    for name, data in files.items():
        (cur / name).write_bytes(data)
    edit_json(cur / "products.json",
              lambda p: {**p, "files": {**p["files"], "mesh": sorted(files)}})


_damaged("volume.vtu damaged", lambda r: _add_mesh(r, {"volume.vtu": b"<VTKFile"}),
         ("volume.vtu", "cannot be read", "dotshell mesh"), command="forward")
_damaged("optodes.json a list", lambda r: _add_mesh(r, {"volume.vtu": _cube_vtu(),
                                                      "optodes.json": b"[1, 2]"}),
         ("optodes.json", "is not a valid optodes file", "dotshell mesh"), command="forward")


@case("damaged run", "forward's mesh directory outside the run", ("--mesh-dir", "inside the run"))
def _(env):
    run = env.run()
    return ["forward", str(run), "--mesh-dir", "../../.."]


def _events_readable(env, err):
    from dotshell.run.store import RunStore

    run = _the_run(env)
    lines = (run / "events.jsonl").read_bytes().splitlines()
    cut = lines.index(b'{"event": "FrameCap')  # left alone, on its own line
    assert all(json.loads(line) for line in lines[cut + 1:])  # the next job's events are whole
    events = RunStore(run).events()
    assert events[-1]["event"] != "FrameCap" and len(events) == len(lines) - 1


@case("damaged run", "the event log cut mid-line by a kill", (), code=0,
      then=_events_readable)
def _(env):
    run = env.run()
    with open(run / "events.jsonl", "ab") as f:
        f.write(b'{"event": "FrameCap')  # a writer killed mid-line
    return ["reconstruct", str(run)]


# ==== 13. commands on runs in each lifecycle state ===============================================

def _hold_lock(env: Env, run: Path) -> int:
    """Another process (not dotshell) holds the run's lock, as a running scan would."""
    code = ("import fcntl, json, os, sys, time\n"
            f"fd = os.open({str(run / '.lock')!r}, os.O_RDWR | os.O_CREAT)\n"
            "fcntl.flock(fd, fcntl.LOCK_EX)\n"
            "os.write(fd, json.dumps({'pid': os.getpid(), 'host': 'bench', 'command': 'scan', "
            "'since': 'now'}).encode())\n"
            "print('locked', flush=True)\ntime.sleep(120)\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "locked"
    env.cleanups.append(lambda: (proc.kill(), proc.wait()))
    edit_json(run / "manifest.json", lambda m: {**m, "status": "running",
                                                "job": {"command": "scan", "pid": proc.pid}})
    return proc.pid


def _running(command: str, code: int = 2):
    def setup(env):
        run = env.run()
        env.holder = _hold_lock(env, run)
        return [command, str(run)]
    return setup


for command in ("reconstruct", "mesh", "forward", "resume"):
    case("states", f"{command} of a running run",
         ("is being written by `dotshell scan` (pid", "on bench", "dotshell inspect"))(
        _running(command))


@case("states", "inspect of a running run", ("status: running",), code=0)
def _(env):
    return _running("inspect")(env)


def _interrupted(env: Env, kind: str = "base") -> Path:
    run = env.run(kind)
    edit_json(run / "manifest.json", lambda m: {**m, "status": "running",
                                                "job": {"command": "scan", "pid": 999999}})
    return run


def _status_is(status: str):
    def then(env, err):
        run = _the_run(env)
        assert manifest(run)["status"] == status, manifest(run)["status"]
    return then


@case("states", "resume of a completed run", ("is completed; nothing to resume",
                                              "dotshell reconstruct"))
def _(env):
    return ["resume", str(env.run())]


@case("states", "resume of a directory that is not a run", ("not a dotshell run directory",))
def _(env):
    return ["resume", str(env.tmp)]


@case("states", "inspect of an interrupted run", (), code=0)
def _(env):
    return ["inspect", str(_interrupted(env))]


@case("states", "reconstruct of an interrupted, fully captured run", (), code=0,
      state_may_change=True, then=_status_is("completed"))
def _(env):
    return ["reconstruct", str(_interrupted(env))]


@case("states", "reconstruct of an aborted run (the complete views only)",
      (), code=0, then=_status_is("aborted"))
def _(env):
    return ["reconstruct", str(env.run("aborted"))]


@case("states", "reconstruct of a run without a complete view",
      ("no view of", "is completely captured", "dotshell resume"))
def _(env):
    return ["reconstruct", str(env.run("empty"))]


@case("states", "mesh of a run without a cloud", ("no view of", "dotshell resume"))
def _(env):
    return ["mesh", str(env.run("empty"))]


@case("states", "normalize of a run without trans-illumination",
      ("no trans-illumination frames",))
def _(env):
    return ["normalize", str(env.run())]


@case("states", "resume of an interrupted run whose camera now gives 8-bit frames",
      ("captured at 12 bit", "now reports 8 bit", "bit_depth"), state_may_change=True,
      then=_status_is("failed"))
def _(env):
    run = _interrupted(env, "aborted")
    text = (run / "profile.toml").read_text().replace("bit_depth = 12", "bit_depth = 8")
    replace_file(run / "profile.toml", text)
    return ["resume", str(run)]


# ==== 14. two writers at once ===================================================================

@case("writers", "reconstruct while another dotshell job holds the run",
      ("being written by `dotshell mesh`", f"pid {os.getpid()}"))
def _(env):
    from dotshell.run.lifecycle import RunLock

    run = env.run()
    lock = RunLock(run)
    lock.acquire("mesh")
    env.cleanups.append(lock.release)
    return ["reconstruct", str(run)]


@case("writers", "a scan into a directory another scan just made", (), code=0)
def _(env):
    """Two scans started in the same second get two run directories."""
    from datetime import datetime

    out = env.tmp / "runs"
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    for s in (stamp, datetime.fromtimestamp(time.time() + 1).strftime("%Y%m%d-%H%M%S")):
        (out / f"{s}_sim-metal-cylinder").mkdir(parents=True, exist_ok=True)
        (out / f"{s}_sim-metal-cylinder" / "mine").write_text("the other scan's")
    return ["scan", str(env.profile()), "--out", str(out)]


# ==== 15. orphan temporary files =================================================================

ORPHANS = (".manifest.json.k2j3h4.tmp", "current/.cloud.ply.abc123.tmp",
           "gen/001/views/.view_000.ply.x8y9.tmp")


def _orphans_removed(env, err):
    run = _the_run(env)
    for name in ORPHANS:
        assert not (run / name).exists(), name
    assert (run / "notes.tmp").is_file()  # not dotshell's: kept


def _with_orphans(env, command: str) -> list[str]:
    run = env.run()
    for name in ORPHANS:
        (run / name).write_bytes(b"half a file")
    (run / "notes.tmp").write_text("a user's file")
    return [command, str(run)]


@case("orphans", "removed by the next job", ("removed", ".cloud.ply.abc123.tmp",
                                             "left by an interrupted job"), code=0,
      then=_orphans_removed)
def _(env):
    return _with_orphans(env, "reconstruct")


@case("orphans", "kept by a read-only command", (), code=0,
      then=lambda env, err: [(_the_run(env) / n).stat() for n in ORPHANS])
def _(env):
    return _with_orphans(env, "inspect")


# ==== 16. permissions ===========================================================================

def _modes(umask: int):
    def then(env, err):
        run = only_run(env.tmp / "runs")
        want_file, want_dir = 0o666 & ~umask, 0o777 & ~umask
        bad = {str(p.relative_to(run)): oct(p.stat().st_mode & 0o777) for p in run.rglob("*")
               if not p.is_symlink() and (p.stat().st_mode & 0o777) != (
                   want_dir if p.is_dir() else want_file)}
        assert not bad, (oct(want_file), bad)
    return then


for umask in (0o002, 0o022, 0o077):
    @case("permissions", f"umask {umask:03o}", (), code=0, then=_modes(umask))
    def _(env, umask=umask):
        old = os.umask(umask)
        env.cleanups.append(lambda: os.umask(old))
        return ["scan", str(env.profile(mesh={"after_scan": False})), "--out",
                str(env.tmp / "runs")]


# ==== real file systems (a private tmpfs) ========================================================

@needs_tmpfs
def test_a_real_full_disk_during_a_scan(tmp_path: Path) -> None:
    """A 400 kB tmpfs: the first view's frames fit, the second's do not; the event log and the
    manifest meet the full disk too."""
    prof = write_profile(tmp_path / "p.toml", tiny_profile_dict())
    mnt = tmp_path / "mnt"
    report, err = in_tmpfs(mnt, "size=480k", [["scan", str(prof), "--out", f"{mnt}/runs"]])
    assert report["code"] == 2, err
    assert "Traceback" not in err and "No space left on device" in err, err
    (run,) = report["runs"]
    m = run["manifest"]
    assert m["status"] in ("failed", "running"), m["status"]
    for v in m["views"]:
        assert v["frames"] == run["frames"].get(f"view_{v['index']:03d}", 0), (v, run["frames"])
    assert not run["tmp"], run["tmp"]


@needs_tmpfs
def test_a_real_file_system_out_of_inodes(tmp_path: Path) -> None:
    prof = write_profile(tmp_path / "p.toml", tiny_profile_dict())
    mnt = tmp_path / "mnt"
    report, err = in_tmpfs(mnt, "size=64m,nr_inodes=24", [["scan", str(prof), "--out",
                                                           f"{mnt}/runs"]])
    assert report["code"] == 2, err
    assert "Traceback" not in err and "No space left on device" in err, err
    for run in report["runs"]:
        for v in run["manifest"]["views"]:
            assert v["frames"] == run["frames"].get(f"view_{v['index']:03d}", 0)


@needs_tmpfs
def test_reprocessing_a_run_on_a_read_only_file_system(tmp_path: Path) -> None:
    prof = write_profile(tmp_path / "p.toml", tiny_profile_dict())
    mnt = tmp_path / "mnt"
    report, err = in_tmpfs(mnt, "size=64m", [["scan", str(prof), "--out", f"{mnt}/runs"],
                                             ["!", f"mount -o remount,ro {mnt}"],
                                             ["reconstruct", "{run}"]])
    assert report["code"] == 2, err
    assert "Traceback" not in err and "read-only file system" in err.lower(), err
    assert "cp -a" in err, err
    assert report["runs"][0]["manifest"]["status"] == "completed"


def test_debug_shows_the_traceback(tmp_path: Path, capsys) -> None:
    prof = write_profile(tmp_path / "p.toml", tiny_profile_dict(scan__exposure_ms=NAN))
    assert main(["--debug", "check", str(prof)]) == 2
    assert "Traceback" in capsys.readouterr().err
    assert main(["check", str(prof), "--debug"]) == 2
    assert "Traceback" in capsys.readouterr().err


def test_progress_shows_a_stalled_step_as_stalled() -> None:
    from rich.console import Console

    from dotshell.cli.common import ScanProgress
    from dotshell.events import FrameCaptured, ScanStarted

    view = ScanProgress(Console(file=open(os.devnull, "w")))
    view(ScanStarted(run_dir="r", profile="p", n_views=2, frames_per_view=3))
    view(FrameCaptured(view=0, index=0, name="white"))
    column = view.progress.columns[-1]
    task = view.progress.tasks[1]
    assert "stalled" not in str(column.render(task))
    view.last_advance[task.id] = time.monotonic() - 95
    assert str(column.render(task)) == "stalled 95 s"


def test_a_stop_signal_never_cuts_a_queue_operation_short() -> None:
    """A signal raised in the middle of ``Queue.put`` (inside ``Condition.notify``) loses the
    frame writer's wake-up and the scan hangs for ever (seen under SIGTERM): the frame writer's
    queue operations defer the stop to their end."""
    import signal as sig

    from dotshell.run.lifecycle import Interrupted, interrupts, signals_deferred

    reached_end = False
    with pytest.raises(Interrupted) as stopped:
        with interrupts(notify=lambda text: None), signals_deferred():
            os.kill(os.getpid(), sig.SIGTERM)
            time.sleep(0.05)  # the handler has run by now, and did not raise here
            reached_end = True
    assert reached_end and stopped.value.signame == "SIGTERM"


# ==== a slow host (issue 33) =====================================================================

@pytest.mark.parametrize("acquisition", ["sequenced", "show-capture"])
def test_a_slow_simulator_never_times_out(acquisition: str, tmp_path: Path, monkeypatch,
                                          capsys) -> None:
    """The simulated camera's rendering is slowed (every render waits 50 ms more, as on a
    host whose cores other work holds) while its calls' timeouts are 0.2 s: rendering is the
    simulator's own compute, so the scan completes. Without ``RigContext.computing`` the
    sequence's ``read_armed()`` (30 renders) and each capture failed with DeviceTimeout. A
    device that really stalls still times out: tests/test_device_handles.py."""
    import dotshell.rig.handles as handles
    from dotshell_sim.render import Renderer

    monkeypatch.setattr(handles, "GRACE_S", 0.05)
    render = Renderer.render
    slowed = []

    def slow_render(self, view, radiance):
        slowed.append(1)
        time.sleep(0.05)
        return render(self, view, radiance)

    monkeypatch.setattr(Renderer, "render", slow_render)
    prof = write_profile(tmp_path / "p.toml", tiny_profile_dict(
        scan__acquisition=acquisition, camera__timeouts={"capture": 0.2, "other": 0.2},
        mesh={"after_scan": False}))
    code = main(["scan", str(prof), "--out", str(tmp_path / "runs")])
    err = capsys.readouterr().err
    assert code == 0, err
    assert manifest(only_run(tmp_path / "runs"))["status"] == "completed"
    assert len(slowed) >= 60  # 2 views of 30 frames, each rendered more slowly than 0.2 s / 4


# ==== generations keep what they did not recompute (issue 33) ===================================

def _validation_kept(env: Env, err: str) -> None:
    run = env.tmp / "run1"
    before = json.loads((env.shared("base") / "report.json").read_text())["validation"]
    report = json.loads((run / "report.json").read_text())
    assert report["generation"] == 2 and report["validation"] == before
    assert "validation" not in report.get("dropped", [])
    assert main(["validate", str(run), "--out", str(env.tmp / "val")]) == 0
    assert (env.tmp / "val" / "validation.csv").read_text().count("\n") == 2


@case("generations", "validation survives `mesh`", (), code=0, then=_validation_kept,
      state_may_change=True)
def _(env):
    return ["mesh", str(env.run())]


@case("generations", "validation survives `mesh` of a run made before it was listed", (),
      code=0, then=_validation_kept, state_may_change=True)
def _(env):
    run = env.run()
    products = run / "gen" / "001" / "products.json"
    edit_json(products, lambda p: {**p, "files": {k: v for k, v in p["files"].items()
                                                  if k != "validation"}})
    return ["mesh", str(run)]


# ==== dead ends offer the way out (issue 33) =====================================================

def _cut_stack(run: Path, view: int = 1, keep: float = 1 / 3) -> Path:
    stack = run / "frames" / f"view_{view:03d}.tif"
    os.truncate(stack, int(stack.stat().st_size * keep))
    return run


@case("dead ends", "inspect counts only the whole pages of a cut stack",
      ("views: 1 of 2 complete", "view 1: 10 of its 30 frames on disk",
       "resume {tmp}/run1 --view 1"), code=0)
def _(env):
    run = _cut_stack(env.run())
    assert frames_on_disk(run, 1) == 10  # counted by tifffile, not by dotshell
    return ["inspect", str(run)]


@case("dead ends", "resume names a cut stack and the way out",
      ("view 1 has 10 of its 30 frames on disk", "cut or deleted",
       "dotshell resume {tmp}/run1 --view 1"))
def _(env):
    return ["resume", str(_cut_stack(env.run()))]


@case("dead ends", "resume names a deleted stack and the way out",
      ("view 0 has 0 of its 30 frames on disk", "--view 0"))
def _(env):
    run = env.run()
    (run / "frames" / "view_000.tif").unlink()
    return ["resume", str(run)]


@case("dead ends", "reconstruct on a cut stack offers the re-capture",
      ("view_001.tif", "dotshell resume {tmp}/run1 --view 1"))
def _(env):
    return ["reconstruct", str(_cut_stack(env.run()))]


@case("dead ends", "resume --view of a view the run does not have", ("--view 5", "views 0 to 1"))
def _(env):
    return ["resume", str(env.run()), "--view", "5"]


def test_resume_view_captures_a_cut_stack_again(shared, tmp_path: Path, capsys) -> None:
    """The way out works: `resume RUN --view 1` sets the cut stack aside (kept), captures the
    view again and publishes a new generation; the run's counts are true."""
    import subprocess as sp

    run = tmp_path / "run"
    sp.run(["cp", "-a", str(shared("base")), str(run)], check=True)
    cut = (_cut_stack(run) / "frames" / "view_001.tif").read_bytes()
    assert main(["resume", str(run), "--view", "1"]) == 0, capsys.readouterr().err
    m = manifest(run)
    assert m["status"] == "completed" and [v["frames"] for v in m["views"]] == [30, 30]
    counts_are_true(run)
    assert (run / "frames" / "view_001.partial-1.tif").read_bytes() == cut
    err = " ".join(capsys.readouterr().err.split())
    report = json.loads((run / "report.json").read_text())
    for v in report["views"]:  # both views measured and printed, the resumed one too
        q = v["quality"]
        assert q["decoded_pct"] == round(100 * v["decoded"] / v["pixels"], 2)
        assert (f"view {v['view'] + 1}: {v['points']} points; decoded {q['decoded_pct']:.1f} % "
                f"of the image, {q['reversals']} neighbour reversals") in err
    assert main(["inspect", str(run)]) == 0
    assert "views: 2 of 2 complete, 60 frames on disk" in capsys.readouterr().out


# ==== a run's status is true after every failure path (issue 33) =================================

def _status_unchanged(kind: str):
    def then(env: Env, err: str) -> None:
        m = manifest(env.tmp / "run1")
        assert m["status"] == kind and m.get("job") is None, m  # never left "running"
        assert main(["inspect", str(env.tmp / "run1")]) == 0
    return then


@case("states", "resume on a disk that is still full",
      ("the disk is full", "no space left on device", "free disk space", "run is unchanged"),
      then=_status_unchanged("aborted"))
def _(env):
    run = env.run("aborted")
    FullDisk(env.monkeypatch, run, free=20_000)
    return ["resume", str(run)]


@case("states", "mesh on a full disk names the disk and keeps the status",
      ("the disk is full", "free disk space"), then=_status_unchanged("completed"))
def _(env):
    run = env.run()
    FullDisk(env.monkeypatch, run, free=20_000)
    return ["mesh", str(run)]


# ==== every long computation bounded by what its input asks (issue 33) ===========================

@case("bounds", "mesh --node-distance 0.001 (ran for more than 300 s)",
      ("--node-distance 0.001 mm", "smallest node distance", "0.05 mm"))
def _(env):
    return ["mesh", str(env.run()), "--node-distance", "0.001"]


@case("bounds", "a mesh whose node count would exceed the limit",
      ("a mesh at 0.06 mm would have about", "nodes", "5,000,000", "larger node distance"))
def _(env):
    import tomllib

    import tomli_w

    run = env.run()
    raw = tomllib.loads((run / "profile.toml").read_text())
    raw["mesh"]["also_node_distances_mm"] = [0.06]
    replace_file(run / "profile.toml", tomli_w.dumps(raw))
    return ["mesh", str(run)]


@case("bounds", "normalize --min-sin-beta 2 (sin β ≤ 1)",
      ("--min-sin-beta", "[normalize.min_sin_beta] = 2.0", "[0.0, 1.0]"))
def _(env):
    return ["normalize", str(env.run()), "--min-sin-beta", "2"]


# ==== `check` validates what the scan will use, with the scan's bounds (issue 33) ================

_profile("check bounds", "exposure 1e308", ("[scan.exposure_ms] = 1e+308", "[0.001, 600000.0] ms"),
         scan__exposure_ms=1e308)
_profile("check bounds", "settle_ms 1e12 (the scan hung)", ("[scan.settle_ms] = 1000000000000.0",
                                                            "[0.0, 600000.0] ms"),
         scan__settle_ms=1e12)
_profile("check bounds", "ROI radius 0", ("[processing.roi.radius_mm] = 0.0", "[0.001, +inf] mm"),
         processing__roi__radius_mm=0.0)
_profile("check bounds", "ROI z_min above z_max",
         ("[processing.roi] z_min_mm = 30 is not below z_max_mm = 10", "z_min_mm < z_max_mm"),
         processing__roi__z_min_mm=30.0, processing__roi__z_max_mm=10.0)


# ==== a user script's own error shows its traceback (issue 33) ===================================

@pytest.mark.parametrize("source, says", [
    ("x = 1\ndef f():\n    return 1 / 0\nf()\n", ("line 4, in <module>", "line 3, in f",
                                                    "ZeroDivisionError: division by zero")),
    ("x = (1,\n", ("line 1", "SyntaxError", "never closed")),
], ids=["raises", "syntax error"])
def test_a_scripts_own_error_shows_its_traceback(source, says, tmp_path, capsys) -> None:
    """docs/tui.md promises the traceback; it said "internal error … a bug in dotshell"."""
    script = tmp_path / "mine.py"
    script.write_text(source)
    code = main(["script", str(script), "--profile",
                 str(write_profile(tmp_path / "p.toml", tiny_profile_dict()))])
    err = capsys.readouterr().err
    assert code == 1, err
    assert f"script {script} failed" in err and "internal error" not in err, err
    for s in says:
        assert s in err, (s, err)
    assert "console.py" not in err  # dotshell's own frames are left out


# ==== files that are not what they seem (issue 33) ===============================================

@case("odd files", "a FIFO given as the profile", ("{tmp}/p.toml is not a regular file", "FIFO"))
def _(env):
    os.mkfifo(env.tmp / "p.toml")
    return ["check", str(env.tmp / "p.toml")]


@case("odd files", "a FIFO is not listed among the profiles",
      ("{tmp}/nope.toml does not exist", "profiles in {tmp}: real.toml"))
def _(env):
    os.mkfifo(env.tmp / "fifo.toml")
    env.profile("real.toml")
    return ["check", str(env.tmp / "nope.toml")]


@case("odd files", "a 50k-deep TOML array as the profile", ("{tmp}/p.toml", "nested too deeply"))
def _(env):
    env.file("p.toml", "a = " + "[" * 50_000 + "]" * 50_000 + "\n")
    return ["check", str(env.tmp / "p.toml")]


@case("odd files", "a 100k-deep JSON manifest", ("{tmp}/run1/manifest.json", "not valid json",
                                                 "maximum recursion depth"))
def _(env):
    run = env.run()
    replace_file(run / "manifest.json", "[" * 100_000 + "]" * 100_000)
    return ["inspect", str(run)]


@case("odd files", "a 100k-deep JSON calibration", ("{tmp}/cal.json", "not valid json"))
def _(env):
    env.file("cal.json", "[" * 100_000 + "]" * 100_000)
    return ["reconstruct", str(env.run()), "--calibration", str(env.tmp / "cal.json")]


@case("odd files", "serve --socket in a missing directory",
      ("--socket {tmp}/nowhere/rig.sock", "{tmp}/nowhere does not exist", "mkdir -m 700"))
def _(env):
    return ["serve", str(env.profile()), "--socket", str(env.tmp / "nowhere" / "rig.sock")]


@case("states", "full disk while writing the mesh names the file",
      ("no space left on device", "{tmp}/run1/gen/002/", "free disk space"),
      then=_status_unchanged("completed"))
def _(env):
    run = env.run()
    FullDisk(env.monkeypatch, run / "gen", free=30_000)  # the reserve fits, the mesh does not
    return ["mesh", str(run)]


# ==== resource exhaustion names the limit (issue 33) =============================================

def test_an_address_space_limit_exits_2_naming_it(tmp_path: Path) -> None:
    """`ulimit -v 700000`: the scan cannot start its threads or get its memory; it said
    "internal error: RuntimeError: can't start new thread" with exit 1 and, from a shell
    without OPENBLAS_NUM_THREADS, "OpenBLAS error: Memory allocation still failed" (exit 1)
    before the command could say anything."""
    import resource

    prof = write_profile(tmp_path / "p.toml", tiny_profile_dict())
    limit = 700_000 * 1024

    def limited() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    env = {k: v for k, v in os.environ.items()  # a user's shell: no BLAS thread settings
           if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")}
    proc = subprocess.run([sys.executable, "-m", "dotshell.cli.app", "scan", str(prof), "--out",
                           str(tmp_path / "runs")], preexec_fn=limited, capture_output=True,
                          text=True, timeout=600, env=env)
    assert proc.returncode == 2, proc.stderr
    assert "ulimit -v 700000 kB" in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
    assert "internal error" not in proc.stderr, proc.stderr


def test_a_thread_that_cannot_start_exits_2_naming_the_limits(tmp_path, monkeypatch,
                                                              capsys) -> None:
    import resource

    def refuse(self):
        raise RuntimeError("can't start new thread")

    monkeypatch.setattr(threading.Thread, "start", refuse)
    soft, hard = resource.getrlimit(resource.RLIMIT_NPROC)
    prof = write_profile(tmp_path / "p.toml", tiny_profile_dict())
    assert main(["scan", str(prof), "--out", str(tmp_path / "runs")]) == 2
    err = capsys.readouterr().err
    assert "could not start a thread" in err and "thread limit" in err, err
    if soft != resource.RLIM_INFINITY:
        assert f"ulimit -u {soft}" in err


def _validated_now(env: Env, err: str) -> None:
    kept = json.loads((env.shared("base") / "report.json").read_text())["validation"]
    row = (env.tmp / "val" / "validation.csv").read_text().splitlines()[1].split(",")
    assert float(row[4]) == pytest.approx(kept["mean_rel_error_pct"], abs=1e-4), row  # CSV: 4 d.


@case("generations", "validate a run whose report lacks the validation", (), code=0,
      then=_validated_now)
def _(env):
    run = env.run()
    edit_json(run / "report.json", lambda r: {k: v for k, v in r.items() if k != "validation"})
    return ["validate", str(run), "--out", str(env.tmp / "val")]
