"""The fault matrix: bad input and hostile conditions, each through the real `dotshell`
command. Every case asserts the exit code, that the message names the thing and the fix with no
traceback, and that no file that existed before was changed or lost."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import pytest

from conftest import ROOT, small_profile_dict, write_profile
from dotshell.cli import main


def digest_tree(root: Path) -> dict[str, str]:
    if not root.exists():
        return {}
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and not p.is_symlink()}


@dataclass
class Case:
    """One fault: ``setup(tmp)`` returns the command's arguments; the command must exit with
    ``code`` and print every string of ``says`` on stderr."""

    name: str
    setup: Callable[[Path], list[str]]
    says: tuple[str, ...]
    code: int = 2
    watch: Callable[[Path], Path] = field(default=lambda tmp: tmp)


def tiny_profile(tmp: Path, name: str = "p.toml", **changes) -> Path:
    raw = small_profile_dict(factor=0.1, views=2)
    raw["camera"]["settings"]["supersample"] = 1
    raw["outputs"] = {"previews": False}
    for dotted, value in changes.items():
        *path, key = dotted.split("__")
        d = raw
        for p in path:
            d = d.setdefault(p, {})
        d[key] = value
    return write_profile(tmp / name, raw)


def _profile_case(name: str, says: tuple[str, ...], **changes) -> Case:
    return Case(name, lambda tmp: ["check", str(tiny_profile(tmp, **changes))], says)


def _set_case(name: str, setting: str, says: tuple[str, ...]) -> Case:
    return Case(name, lambda tmp: ["check", str(tiny_profile(tmp)), "--set", setting], says)


def _out_is_a_file(tmp: Path) -> list[str]:
    (tmp / "afile").write_text("x")
    return ["scan", str(tiny_profile(tmp)), "--out", str(tmp / "afile")]


def _out_not_writable(tmp: Path) -> list[str]:
    """/sys refuses new directories even to root (chmod would not stop root)."""
    if os.access("/sys", os.W_OK) and os.getuid() != 0:
        pytest.skip("/sys is writable here")
    return ["scan", str(tiny_profile(tmp)), "--out", "/sys/dotshell-runs"]


def _unmeasured_axis(tmp: Path) -> list[str]:
    from dotshell.plugins import PluginManager
    from dotshell.profile import load_profile
    from dotshell.rig import Rig

    prof = tiny_profile(tmp)
    pm = PluginManager()
    pm.load_entry_points()
    calib = Rig(load_profile(prof, pm), pm).calibration().to_dict()
    calib["turntable"]["measured"] = False
    (tmp / "cal.json").write_text(json.dumps(calib))
    return ["scan", str(prof), "--out", str(tmp / "runs"), "--calibration", str(tmp / "cal.json")]


CASES = [
    Case("calibration without a measured axis", _unmeasured_axis,
         ("no measured turntable axis", "dotshell calibrate", "scan.views=1")),
    Case("every point outside the region of interest",
         lambda tmp: ["scan", str(tiny_profile(tmp, processing__roi__radius_mm=0.01)), "--out",
                      str(tmp / "runs")],
         ("were triangulated but no point is left", "outside the region of interest",
          "[processing.roi]")),
    _profile_case("nan exposure", ("[scan.exposure_ms] = nan", "finite"),
                  scan__exposure_ms=float("nan")),
    _profile_case("inf settle", ("[scan.settle_ms] = inf", "finite"), scan__settle_ms=float("inf")),
    _profile_case("nan roi radius", ("radius_mm", "finite"),
                  processing__roi__radius_mm=float("nan")),
    _profile_case("inf focal", ("focal_px", "finite"),
                  camera__settings__focal_px=float("inf")),
    _profile_case("nan node distance", ("node_distance_mm", "finite"),
                  mesh__node_distance_mm=float("nan")),
    _set_case("--set nan", "scan.exposure_ms=nan", ("exposure_ms", "finite")),
    _set_case("--set -inf", "scan.settle_ms=-inf", ("settle_ms", "finite")),
    Case("--out is a file", _out_is_a_file, ("afile", "not a directory")),
    Case("--out not writable", _out_not_writable, ("/sys/dotshell-runs", "--out")),
]


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_fault(case: Case, tmp_path: Path, capsys) -> None:
    args = case.setup(tmp_path)
    before = digest_tree(case.watch(tmp_path))
    try:
        code = main(args)
    finally:
        for p in tmp_path.rglob("*"):  # let pytest clean read-only test directories
            if p.is_dir():
                p.chmod(0o755)
    err = capsys.readouterr().err
    assert code == case.code, err
    assert "Traceback" not in err
    for s in case.says:
        assert s.lower() in err.lower(), (s, err)
    after = digest_tree(case.watch(tmp_path))
    assert all(after.get(k) == v for k, v in before.items()), "a file changed or was lost"


def test_debug_shows_the_traceback(tmp_path: Path, capsys) -> None:
    prof = tiny_profile(tmp_path, scan__exposure_ms=float("nan"))
    assert main(["--debug", "check", str(prof)]) == 2
    assert "Traceback" in capsys.readouterr().err
    assert main(["check", str(prof), "--debug"]) == 2
    assert "Traceback" in capsys.readouterr().err


def test_progress_shows_a_stalled_step_as_stalled() -> None:
    import time

    from rich.console import Console

    from dotshell.cli import ScanProgress
    from dotshell.events import FrameCaptured, ScanStarted

    view = ScanProgress(Console(file=open(os.devnull, "w")))
    view(ScanStarted(run_dir="r", profile="p", n_views=2, frames_per_view=3))
    view(FrameCaptured(view=0, index=0, name="white"))
    column = view.progress.columns[-1]
    task = view.progress.tasks[1]
    assert "stalled" not in str(column.render(task))
    view.last_advance[task.id] = time.monotonic() - 95
    assert str(column.render(task)) == "stalled 95 s"
