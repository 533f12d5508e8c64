"""pytest helpers for plugin authors, registered as a pytest11 plugin (available in any test
suite once dotshell is installed).

Fixtures:
    dotshell_pm: a fresh :class:`~dotshell.plugins.PluginManager` with all installed entry
        points loaded (load errors in ``dotshell_pm.load_errors``).

Functions:
    assert_backend_conforms(pm, role, name, settings=None): validate ``settings`` against the
        backend's schema, build it, and check that it satisfies the role's protocol.
"""

from __future__ import annotations

from typing import Any

import pytest

from dotshell.backends import RigContext
from dotshell.coding import PatternCoding
from dotshell.plugins import PluginManager


@pytest.fixture
def dotshell_pm() -> PluginManager:
    pm = PluginManager()
    pm.load_entry_points()
    return pm


def assert_backend_conforms(pm: PluginManager, role: str, name: str,
                            settings: dict[str, Any] | None = None) -> Any:
    """Build backend ``name`` for ``role`` and assert it satisfies the role's protocol."""
    from dotshell.rig import PROTOCOLS

    if role == "coding":
        obj = pm.create(role, name, settings, None, "test")
        assert isinstance(obj, PatternCoding), f"{name} is not a PatternCoding"
    elif role in PROTOCOLS:
        obj = pm.create(role, name, settings, RigContext(), "test")
        from dotshell.devices import missing_members

        missing = missing_members(obj, PROTOCOLS[role])
        assert not missing, f"{name} lacks {missing} of the {role} protocol"
    else:
        obj = pm.create(role, name, settings, None, "test")
        if role == "exporter":
            assert callable(getattr(obj, "export", None)), f"{name} has no export(run_dir)"
    return obj
