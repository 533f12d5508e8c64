"""Plugin manifests: a plugin's backends declared as data, imported only when one is used.

A plugin package may ship a ``dotshell.toml`` next to its ``__init__.py`` (package data, so it
is in the wheel)::

    # optional: a module with workflow hooks, imported and registered at start-up
    hooks = "my_package.events"

    [[backends]]
    kind = "exporter"                # a role of dotshell.backends.ROLES
    name = "xyz-text"                # what profiles write: backend = "xyz-text"
    summary = "merged cloud as plain-text XYZ (mm)"   # one line for `dotshell plugins`
    python_name = "my_package.backends:xyz_text"      # module:attr
    usb_ids = ["2341:0043"]          # optional, for `dotshell ports`

``python_name`` names a :class:`~dotshell.backends.Backend`, or a function of no arguments
returning one; its module is imported the first time a profile or command uses the backend.
The plugin manager finds the manifest through the plugin's ``dotshell`` entry point without
importing the package (:func:`find_manifest`). A plugin without a manifest is imported at
start-up and asked for its backends through the hooks of :mod:`dotshell.hookspecs`, as before.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import tomllib
from dataclasses import dataclass
from importlib.machinery import PathFinder
from pathlib import Path
from typing import Any, Callable

from dotshell.backends import ROLES, Backend
from dotshell.errors import PluginError

#: the file name of a manifest inside a plugin's package directory
MANIFEST_NAME = "dotshell.toml"


@dataclass(frozen=True)
class ManifestBackend:
    """One backend as its manifest declares it (nothing imported yet)."""

    kind: str
    name: str
    summary: str
    python_name: str
    usb_ids: tuple[str, ...] = ()

    def load(self) -> Backend:
        """Import ``python_name`` and return its :class:`Backend`, with the manifest's summary
        and USB ids. Raises :class:`PluginError` saying what is wrong (any import-time
        failure of the plugin's module included)."""
        module, _, attr = self.python_name.partition(":")
        try:
            obj: Any = getattr(importlib.import_module(module), attr)
            backend = obj() if callable(obj) and not isinstance(obj, Backend) else obj
        except (Exception, SystemExit) as exc:  # plugin code: any import-time failure
            raise PluginError(f"importing {self.python_name} raised {type(exc).__name__}: "
                              f"{exc}{raised_at(exc)}") from exc
        if not isinstance(backend, Backend) or backend.name != self.name:
            raise PluginError(f"{self.python_name} must be (or return) a dotshell.backends."
                              f"Backend named {self.name!r}, as the manifest says; it is "
                              f"{short_repr(backend)}")
        return dataclasses.replace(backend, summary=self.summary or backend.summary,
                                   usb_ids=self.usb_ids or backend.usb_ids)


@dataclass(frozen=True)
class Manifest:
    """A plugin's ``dotshell.toml``: its backends and its optional workflow-hook module."""

    path: Path
    backends: tuple[ManifestBackend, ...]
    hooks: str = ""

    def of_kind(self, kind: str) -> list[ManifestBackend]:
        return [b for b in self.backends if b.kind == kind]


def find_manifest(module: str) -> Path | None:
    """The ``dotshell.toml`` of the package ``module`` (an entry point's module), found
    without importing the package or any module in it; None when the module is not a
    package or has no manifest."""
    top, *rest = module.split(".")
    try:
        spec = importlib.util.find_spec(top)  # a top-level name: nothing is imported
    except (ImportError, ValueError):
        return None
    for part in rest:
        if spec is None or spec.submodule_search_locations is None:
            return None
        spec = PathFinder.find_spec(part, list(spec.submodule_search_locations))
    if spec is None or spec.submodule_search_locations is None:
        return None
    for folder in spec.submodule_search_locations:
        path = Path(folder) / MANIFEST_NAME
        if path.is_file():
            return path
    return None


def read_manifest(path: Path) -> Manifest:
    """Parse and check a manifest; :class:`PluginError` naming the file and the entry that
    is wrong and how to write it."""
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise PluginError(f"{path} is not a readable TOML manifest: {exc}") from exc
    entries = data.get("backends", [])
    if not isinstance(entries, list):
        raise PluginError(f"{path}: 'backends' must be an array of tables ([[backends]]).")
    hooks = data.get("hooks", "")
    if not isinstance(hooks, str):
        raise PluginError(f"{path}: 'hooks' must be a module name (a string).")
    return Manifest(path, tuple(_entry(path, i, e) for i, e in enumerate(entries)), hooks)


def _entry(path: Path, index: int, entry: Any) -> ManifestBackend:
    where = f"{path}: [[backends]] #{index + 1}"
    if not isinstance(entry, dict):
        raise PluginError(f"{where} must be a table.")
    for key in ("kind", "name", "python_name"):
        if not isinstance(entry.get(key), str) or not entry[key]:
            raise PluginError(f"{where} needs {key} = \"...\" (a non-empty string).")
    if entry["kind"] not in ROLES:
        raise PluginError(f"{where}: kind = {entry['kind']!r} is not a role. Valid choices: "
                          f"{', '.join(ROLES)}.")
    module, colon, attr = entry["python_name"].partition(":")
    if not (module and colon and attr):
        raise PluginError(f"{where}: python_name = {entry['python_name']!r} must be "
                          "\"package.module:attribute\".")
    usb_ids = entry.get("usb_ids", [])
    if not isinstance(usb_ids, list) or not all(isinstance(u, str) for u in usb_ids):
        raise PluginError(f"{where}: usb_ids must be a list of \"vid:pid\" strings.")
    unknown = sorted(set(entry) - {"kind", "name", "summary", "python_name", "usb_ids"})
    if unknown:
        raise PluginError(f"{where}: unknown key {unknown[0]!r} (keys: kind, name, summary, "
                          "python_name, usb_ids).")
    return ManifestBackend(entry["kind"], entry["name"], str(entry.get("summary", "")),
                           entry["python_name"], tuple(usb_ids))


def backends_of(package: str, kind: str) -> list[Backend]:
    """Every ``kind`` backend of ``package``'s manifest, imported: what a first-party
    package's backend hooks return when it is registered as a plain pluggy plugin (a test,
    a script) rather than discovered through its manifest."""
    path = find_manifest(package)
    if path is None:
        raise PluginError(f"package {package!r} has no {MANIFEST_NAME}.")
    return [b.load() for b in read_manifest(path).of_kind(kind)]


def raised_at(exc: BaseException) -> str:
    """' at FILE:LINE' of the innermost frame of ``exc``'s traceback ('' without one)."""
    import traceback

    last = traceback.extract_tb(exc.__traceback__)[-1:] if exc.__traceback__ else []
    return f" at {last[0].filename}:{last[0].lineno}" if last else ""


def short_repr(value: Any) -> str:
    """``repr(value)``, cut to 80 characters."""
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def lazy_exports(package: str, names: dict[str, str]) -> Callable[[str], Any]:
    """A module ``__getattr__`` (PEP 562) for a light plugin ``__init__``: each public name
    maps to ``"module:attr"`` (relative to ``package``) and is imported on first access, so
    ``from my_plugin import MyCamera`` goes on working while importing ``my_plugin`` imports
    no driver."""

    def __getattr__(name: str) -> Any:
        if name not in names:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        module, _, attr = names[name].partition(":")
        return getattr(importlib.import_module(f"{package}.{module}"), attr)

    return __getattr__
