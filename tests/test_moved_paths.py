"""Old import paths from before the regrouping into rooms keep working one release, with a
DeprecationWarning naming the new path (dotshell.runtime.moved)."""

from __future__ import annotations

import importlib
import subprocess
import sys
import warnings

import pytest

from dotshell.runtime.moved import BECAME_PACKAGES, MOVED


def _fresh_import(code: str) -> subprocess.CompletedProcess:
    """Run ``code`` in a new interpreter with every DeprecationWarning shown."""
    return subprocess.run([sys.executable, "-W", "always::DeprecationWarning", "-c", code],
                          capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("old", sorted(MOVED))
def test_every_old_module_path_is_the_new_module(old):
    new = importlib.import_module(MOVED[old])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sys.modules.pop(old, None)
        assert importlib.import_module(old) is new
    sys.modules.pop(old, None)  # the next test of this path warns again
    assert any(issubclass(w.category, DeprecationWarning) and MOVED[old] in str(w.message)
               for w in caught), [str(w.message) for w in caught]


def test_a_plugin_of_the_old_release_imports_and_is_told_where_to_go():
    """What a third-party plugin written for 0.1 does: names from modules that moved, and names
    read from modules that became packages."""
    proc = _fresh_import(
        "from dotshell.store import RunStore\n"
        "from dotshell.meshfiles import write_surface\n"
        "from dotshell.fem import TriangleSurface\n"
        "import dotshell.run.store, dotshell.fem.meshes\n"
        "assert RunStore is dotshell.run.store.RunStore\n"
        "assert TriangleSurface is dotshell.fem.meshes.TriangleSurface\n"
        "print('ok')\n")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "ok"
    for new in ("dotshell.run.store", "dotshell.fem.meshfiles", "dotshell.fem.meshes.TriangleSurface"):
        assert f"moved to {new};" in proc.stderr, proc.stderr


def test_new_paths_import_without_a_warning():
    proc = _fresh_import("import warnings; warnings.simplefilter('error', DeprecationWarning)\n"
                         + "".join(f"import {m}\n" for m in sorted(set(MOVED.values())
                                                                   | set(BECAME_PACKAGES.values()))))
    assert proc.returncode == 0, proc.stderr


def test_a_name_that_never_existed_is_an_attribute_error():
    import dotshell.fem

    with pytest.raises(AttributeError, match="dotshell.fem.*no_such_name"):
        dotshell.fem.no_such_name  # noqa: B018
