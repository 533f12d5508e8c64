"""Old import paths, kept working for one release after the regrouping into rooms.

Third-party plugins written against dotshell 0.1 import modules that now live in a room
(``dotshell.store`` is :mod:`dotshell.run.store`, ``dotshell.meshfiles`` is
:mod:`dotshell.fem.meshfiles`, …). :data:`MOVED` maps each old module path to its new one; an
import finder installed by ``dotshell/__init__.py`` serves the old path as the new module, with
a :class:`DeprecationWarning` naming the new path. Names that were read from a module which is
now a package (``from dotshell.fem import SurfaceMesh``) are forwarded the same way by that
package's ``__getattr__`` (:func:`forward_to`).
"""

from __future__ import annotations

import importlib
import importlib.machinery
import sys
import warnings
from collections.abc import Callable
from types import ModuleType
from typing import Any

#: old module path -> the module that replaces it (removed in dotshell 0.3)
MOVED: dict[str, str] = {
    "dotshell.cli_batch": "dotshell.cli.batch",
    "dotshell.cli_calibration": "dotshell.cli.calibration",
    "dotshell.cli_completion": "dotshell.cli.completion",
    "dotshell.cli_decode": "dotshell.cli.decode",
    "dotshell.cli_devices": "dotshell.cli.devices",
    "dotshell.cli_entry": "dotshell.cli.entry",
    "dotshell.cli_frames": "dotshell.cli.frames",
    "dotshell.cli_logging": "dotshell.cli.log_setup",
    "dotshell.cli_mesh": "dotshell.cli.mesh",
    "dotshell.cli_normalize": "dotshell.cli.normalize",
    "dotshell.cli_print": "dotshell.cli.common",
    "dotshell.cli_reference": "dotshell.cli.reference",
    "dotshell.cli_server": "dotshell.cli.server",
    "dotshell.cli_shipped": "dotshell.cli.shipped",
    "dotshell.console": "dotshell.session.console",
    "dotshell.fem_kernels": "dotshell.fem.kernels",
    "dotshell.forward": "dotshell.fem.forward",
    "dotshell.optics": "dotshell.fem.optics",
    "dotshell.meshfiles": "dotshell.fem.meshfiles",
    "dotshell.mesh_schema": "dotshell.profile.mesh",
    "dotshell.transillum_schema": "dotshell.profile.transillum",
    "dotshell.calibration.schema": "dotshell.profile.calibration",
    "dotshell.framecheck": "dotshell.run.framecheck",
    "dotshell.frames": "dotshell.run.frames",
    "dotshell.tiffpages": "dotshell.run.tiffpages",
    "dotshell.ply": "dotshell.run.ply",
    "dotshell.store": "dotshell.run.store",
    "dotshell.pipeline.generations": "dotshell.run.generations",
    "dotshell.pipeline.lifecycle": "dotshell.run.lifecycle",
    "dotshell.pipeline.integrity": "dotshell.run.integrity",
    "dotshell.handles": "dotshell.rig.handles",
    "dotshell.rig_checks": "dotshell.rig.checks",
    "dotshell.ports": "dotshell.rig.ports",
    "dotshell.owners": "dotshell.rig.owners",
    "dotshell.hugepages": "dotshell.runtime.hugepages",
    "dotshell.parallel": "dotshell.runtime.parallel",
    "dotshell.numba_cache": "dotshell.runtime.numba_cache",
    "dotshell.compat": "dotshell.runtime.compat",
    "dotshell.server.paths": "dotshell.runtime.paths",
    "dotshell.meshpreview": "dotshell.render.mesh_previews",
}

#: old modules that became packages: their names are now read from this module
BECAME_PACKAGES: dict[str, str] = {
    "dotshell.cli": "dotshell.cli.app",
    "dotshell.fem": "dotshell.fem.meshes",
    "dotshell.profile": "dotshell.profile.loader",
    "dotshell.rig": "dotshell.rig.assembly",
    "dotshell.runtime": "dotshell.runtime.process",
    "dotshell.render": "dotshell.render.previews",
}


def _warn(old: str, new: str) -> None:
    warnings.warn(f"{old} moved to {new}; the old path goes in the next release",
                  DeprecationWarning, stacklevel=3)


class _MovedModuleLoader:
    """Serves an old module path as the module that replaced it (the same module object). A loader
    by protocol (``create_module``/``exec_module``): importlib.abc costs ``dotshell --help`` ~5 ms."""

    def __init__(self, new: str) -> None:
        self.new = new

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType:
        _warn(spec.name, self.new)
        return importlib.import_module(self.new)

    def exec_module(self, module: ModuleType) -> None:
        """Nothing to run: the new module is already imported."""


class MovedModuleFinder:
    """Finds the old module paths of :data:`MOVED`."""

    def find_spec(self, fullname: str, path: Any, target: Any = None) -> importlib.machinery.ModuleSpec | None:
        new = MOVED.get(fullname)
        if new is None:
            return None
        return importlib.machinery.ModuleSpec(fullname, _MovedModuleLoader(new))  # type: ignore[arg-type]


def install() -> None:
    """Put the finder on ``sys.meta_path`` once (called by ``dotshell/__init__.py``)."""
    if not any(isinstance(f, MovedModuleFinder) for f in sys.meta_path):
        sys.meta_path.append(MovedModuleFinder())


def forward_to(package: str) -> Callable[[str], Any]:
    """A package ``__getattr__`` that serves the names of the module the package replaced."""
    new = BECAME_PACKAGES[package]

    def __getattr__(name: str) -> Any:
        if name.startswith("__"):
            raise AttributeError(name)
        module = importlib.import_module(new)
        try:
            value = getattr(module, name)
        except AttributeError:
            raise AttributeError(f"module {package!r} has no attribute {name!r}") from None
        _warn(f"{package}.{name}", f"{new}.{name}")
        return value

    return __getattr__
