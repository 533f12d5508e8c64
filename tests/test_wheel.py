"""What a lab installs is the wheel: the sdist built from a clean copy of the repository, the
wheel built from that sdist (as ``python -m build`` does), installed into a fresh venv outside
the repository, run from another directory. Only the wheel is new: the venv sees the test
venv's site-packages through a path line (no ``.pth`` of the test venv is run, so its editable
dotshell stays out), which keeps this test to seconds of set-up instead of minutes of download.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import tarfile
import time
import tomllib
import zipfile
from pathlib import Path

import numpy as np
import pytest

import opencv_graycode
from conftest import ROOT
from rig_server import user_dirs  # noqa: F401 (a fixture)

#: what a clean copy leaves out: a developer's venvs, runs, builds and caches
IGNORE = shutil.ignore_patterns(".venv*", ".git", "runs", "build", "dist", "site", "*.egg-info",
                                "__pycache__", ".pytest_cache", "bench-results", ".mypy_cache")

#: files the app reads at run time that must be in the wheel (besides every module)
RUNTIME_FILES = ("dotshell/tui/app.tcss", "dotshell/py.typed",
                 "dotshell/shipped/profiles/sim-metal-cylinder.toml",
                 "dotshell/shipped/profiles/lc4500/lc4500_00.png",
                 "dotshell/shipped/layouts/slstudio-graycode.toml",
                 "dotshell/shipped/layouts/opencv-graycode.toml",
                 "dotshell/shipped/docs/index.md", "dotshell/shipped/docs/profiles.md",
                 # the plugins' manifests: without them no first-party backend is found
                 *(f"dotshell_{p}/dotshell.toml" for p in (
                     "sim", "codings", "meshing", "dotio", "normalizers", "serial", "projectors",
                     "cameras")))


def _run(argv: list[str], cwd: Path, env: dict[str, str] | None = None,
         timeout: float = 600) -> subprocess.CompletedProcess:
    r = subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0, f"{argv} failed ({r.returncode}):\n{r.stdout}\n{r.stderr}"
    return r


def _pep517(hook: str, src: Path, out: Path) -> Path:
    """Call setuptools' PEP 517 hook (``build_sdist`` / ``build_wheel``) in ``src``, offline
    (the test venv's setuptools, no isolated build environment); the file it wrote."""
    code = f"from setuptools import build_meta; print(build_meta.{hook}({str(out)!r}))"
    r = _run([sys.executable, "-c", code], cwd=src, env=_clean_env())
    return out / r.stdout.strip().splitlines()[-1]


def _clean_env(**extra: str) -> dict[str, str]:
    """The environment without anything that points Python at the repository."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    return {**env, **extra}


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> dict[str, Path]:
    """The sdist from a clean copy, the wheel from the unpacked sdist."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    shutil.copytree(ROOT, src, symlinks=True, ignore=IGNORE)
    dist = tmp / "dist"
    dist.mkdir()
    sdist = _pep517("build_sdist", src, dist)
    with tarfile.open(sdist) as tar:
        tar.extractall(tmp / "unpacked", filter="data")
    unpacked = next((tmp / "unpacked").iterdir())
    wheel = _pep517("build_wheel", unpacked, dist)
    return {"sdist": sdist, "wheel": wheel, "tmp": tmp}


@pytest.fixture(scope="module")
def venv(built) -> Path:
    """A fresh venv outside the repository with only the wheel installed into it; the
    dependencies come from the test venv's site-packages (a path line, after the venv's own)."""
    v = built["tmp"] / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", str(v)], cwd=built["tmp"])
    py = v / "bin" / "python"
    site = Path(_run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                     cwd=built["tmp"], env=_clean_env()).stdout.strip())
    deps = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    (site / "test-venv-deps.pth").write_text("".join(f"{d}\n" for d in sorted(deps)))
    _run([str(py), "-m", "pip", "install", "--no-deps", "--no-index", "-q", str(built["wheel"])],
         cwd=built["tmp"], env=_clean_env())
    return v


def _dotshell(venv: Path, *args: str, cwd: Path, timeout: float = 600,
              **env: str) -> subprocess.CompletedProcess:
    return _run([str(venv / "bin" / "dotshell"), *args], cwd=cwd, env=_clean_env(**env),
                timeout=timeout)


def test_wheel_holds_every_runtime_file_and_its_metadata(built):
    names = set(zipfile.ZipFile(built["wheel"]).namelist())
    assert set(RUNTIME_FILES) <= names, set(RUNTIME_FILES) - names
    shipped = {Path(n).name for n in names if n.startswith("dotshell/shipped/profiles/")}
    assert {p.name for p in (ROOT / "profiles").rglob("*") if p.is_file()} <= shipped
    assert not any(n.startswith(("tests/", "benchmarks/", "profiles/")) for n in names)
    meta = zipfile.ZipFile(built["wheel"]).read(
        next(n for n in names if n.endswith(".dist-info/METADATA"))).decode()
    assert "License-Expression: BSD-3-Clause" in meta and "License-File: LICENSE" in meta
    assert "Description-Content-Type: text/markdown" in meta
    assert "Classifier: Typing :: Typed" in meta
    assert any(n.endswith(".dist-info/licenses/LICENSE") for n in names)
    check = subprocess.run([sys.executable, "-m", "check_wheel_contents", "--ignore", "W009",
                            str(built["wheel"])], capture_output=True, text=True)
    # W009 (several top-level packages): the first-party plugins are top-level by design
    assert check.returncode == 0, check.stdout + check.stderr


def test_sdist_holds_what_a_checkout_needs(built):
    with tarfile.open(built["sdist"]) as tar:
        names = {n.split("/", 1)[1] for n in tar.getnames() if "/" in n}
    for need in ("LICENSE", "CHANGELOG.md", "dotshell/tui/app.tcss", "profiles/sim-metal-cylinder.toml",
                 "layouts/slstudio-graycode.toml", "docs/index.md", "mkdocs.yml",
                 "tests/conftest.py", "plugins/dotshell_sim/__init__.py"):
        assert need in names, need


def test_installed_dotshell_is_the_wheel_not_the_checkout(venv, tmp_path):
    r = _run([str(venv / "bin" / "python"), "-c", "import dotshell, dotshell_sim; "
              "print(dotshell.__file__); print(dotshell_sim.__file__)"],
             cwd=tmp_path, env=_clean_env())
    for line in r.stdout.split():
        assert Path(line).is_relative_to(venv), r.stdout  # no editable dotshell leaked in
    r = _run([str(venv / "bin" / "python"), "-m", "dotshell", "--version"], cwd=tmp_path,
             env=_clean_env())
    assert r.stdout.strip() == "dotshell 0.1.0"
    r = _dotshell(venv, "docs", cwd=tmp_path)
    assert str(venv) in r.stdout and "index.md" in r.stdout


def _reduced_overrides(factor: float) -> list[str]:
    """``--set`` arguments that scale the shipped metal-cylinder bench's sim camera and
    projector by ``factor`` (what the fast tests use), 2 views, no previews."""
    from dotshell_sim.bench import scale_profile

    raw = tomllib.loads((ROOT / "profiles" / "sim-metal-cylinder.toml").read_text())
    small = scale_profile(raw, factor)
    sets = ["scan.views=2", "outputs.previews=false", "camera.settings.supersample=1"]
    for role in ("camera", "projector"):
        for key, value in small[role]["settings"].items():
            if value != raw[role]["settings"].get(key) and key != "supersample":
                sets.append(f"{role}.settings.{key}={json.dumps(value)}")
    return [a for s in sets for a in ("--set", s)]


def test_installed_scan_of_a_shipped_profile_by_its_bare_name(venv, tmp_path):
    r = _dotshell(venv, "scan", "sim-metal-cylinder", *_reduced_overrides(0.2), "--out", "runs",
                  cwd=tmp_path)
    assert "Mean relative error" in r.stdout, r.stdout
    run = next((tmp_path / "runs").iterdir())
    report = json.loads((run / "report.json").read_text())
    assert report["status"] == "completed" and report["cloud"]["points"] > 1000
    assert abs(report["validation"]["mean_rel_error_pct"]) < 3.0  # the shipped bench, reduced
    assert "Warning" not in r.stderr and "warning" not in r.stderr.lower().replace(
        "warnings", ""), r.stderr  # no library warning reaches the terminal without -v
    bad = subprocess.run([str(venv / "bin" / "dotshell"), "scan", "sim-metal-cylindr"],
                         cwd=tmp_path, env=_clean_env(), capture_output=True, text=True)
    text = " ".join(bad.stderr.split())
    assert bad.returncode == 2 and "sim-metal-cylinder," in text
    assert "dotshell profiles copy NAME my-rig.toml" in text and "Traceback" not in text


def test_installed_decode_with_a_shipped_layout_name(venv, tmp_path):
    """OpenCV's GrayCodePattern sequence (1024×768 projector, the shipped layout's) seen by a
    256×48 camera that sees the projector stretched: every column decoded within 2.5 px."""
    truth = opencv_graycode.write_stretched(tmp_path / "caps", (1024, 768), (256, 48))
    _dotshell(venv, "decode", "--captures", "caps", "--layout", "opencv-graycode", "--format",
              "npy", "--out", "decoded", cwd=tmp_path)
    out = next((tmp_path / "decoded").iterdir())
    column = np.load(out / "column.npy")
    assert np.isfinite(column).mean() > 0.95
    err = np.abs(column - truth[None, :])
    assert np.nanmax(err) < 2.5, np.nanmax(err)


def test_installed_plugins_check_imports_every_declared_backend(venv, tmp_path):
    r = _dotshell(venv, "plugins", "--check", cwd=tmp_path, COLUMNS="200")
    assert "backends load" in r.stdout and "failed" not in r.stdout and "sim-camera" in r.stdout


def test_installed_profiles_list_and_copy(venv, tmp_path):
    r = _dotshell(venv, "profiles", cwd=tmp_path, COLUMNS="200")
    assert "sim-metal-cylinder" in r.stdout and "slstudio-graycode" in r.stdout
    _dotshell(venv, "profiles", "copy", "sim-metal-cylinder-lightcrafter", "my-rig.toml",
              cwd=tmp_path)
    assert (tmp_path / "lc4500" / "lc4500_01.png").is_file()  # the files it names, beside it
    r = _dotshell(venv, "check", "my-rig.toml", cwd=tmp_path)
    assert "profile OK" in r.stdout


def test_installed_tui_draws_its_first_screen(venv, tmp_path, user_dirs, monkeypatch):  # noqa: F811
    from test_tui_pty import PtyScreen

    monkeypatch.delenv("PYTHONPATH", raising=False)  # PtyScreen passes os.environ on
    sets = _reduced_overrides(0.12)
    term = PtyScreen([str(venv / "bin" / "dotshell"), "tui", "sim-metal-cylinder", *sets],
                     tmp_path)
    try:
        term.wait_for("sim-turntable", timeout_s=180)
        term.child.send("\x11")  # ctrl+q: idle, so it just detaches
        term.wait_exit()
    finally:
        if term.child.isalive():
            term.child.terminate(force=True)
        stop = subprocess.run([str(venv / "bin" / "dotshell"), "stop", "sim-metal-cylinder",
                               "--abort"], cwd=tmp_path, env=_clean_env(), capture_output=True,
                              text=True, timeout=300)
    term.child.close()
    assert term.child.exitstatus == 0, term.text()
    assert b"starting a rig server" in term.raw
    assert stop.returncode == 0, stop.stdout + stop.stderr
    t0 = time.monotonic()
    while any(Path(os.environ["XDG_RUNTIME_DIR"]).rglob("*.sock")):
        assert time.monotonic() - t0 < 60, "the server did not go away"
        time.sleep(0.1)
