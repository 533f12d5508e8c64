import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


@pytest.fixture(autouse=True)
def fresh_plugin_manager(monkeypatch):
    """Each test discovers plugins anew (tests add and break plugins)."""
    import dotshell.plugins

    monkeypatch.setattr(dotshell.plugins, "_default", None)


def make_dist(tmp: Path, dist: str, module: str, source: str, ep_name: str) -> Path:
    """Install a tiny distribution by hand (a dist-info with one dotshell entry point)."""
    info = tmp / f"{dist.replace('-', '_')}-1.0.dist-info"  # PEP 427 escaping
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(f"[dotshell]\n{ep_name} = {module}\n")
    (tmp / f"{module}.py").write_text(source)
    return tmp


@pytest.fixture
def broken_plugin(tmp_path, monkeypatch):
    """A plugin whose import fails, installed on sys.path for this test."""
    path = make_dist(tmp_path / "site", "dotshell-broken", "dotshell_broken_mod",
                     "raise ImportError('needs libfoo.so, which is not installed')\n", "broken")
    monkeypatch.syspath_prepend(str(path))
    return path
