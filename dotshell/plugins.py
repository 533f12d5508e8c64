"""Plugin discovery: entry points of the ``dotshell`` group, loaded one by one.

A plugin that fails to import is recorded in :attr:`PluginManager.load_errors` with its name,
distribution and reason; the others still load. ``strict=True`` (``--strict-plugins``) turns
such a failure into a :class:`~dotshell.errors.PluginError` — for plugin authors and CI.
"""

from __future__ import annotations

import importlib.metadata as md
import traceback
from dataclasses import dataclass
from typing import Any, Iterable, Mapping

import pluggy

from dotshell import hookspecs
from dotshell.backends import ROLES, Backend
from dotshell.errors import PluginError
from dotshell.settings import validate_settings

GROUP = "dotshell"


@dataclass(frozen=True)
class PluginLoadError:
    """A plugin entry point that could not be loaded."""

    name: str
    distribution: str
    reason: str

    def __str__(self) -> str:
        return f"plugin {self.name!r} (from {self.distribution}) failed to load: {self.reason}"


@dataclass(frozen=True)
class BackendInfo:
    """A backend together with the plugin and distribution that provide it."""

    role: str
    backend: Backend
    plugin: str
    distribution: str


class PluginManager:
    """Finds plugins and the backends they provide, by role and name."""

    def __init__(self, strict: bool = False) -> None:
        self.strict = strict
        self.pm = pluggy.PluginManager("dotshell")
        self.pm.add_hookspecs(hookspecs)
        self.load_errors: list[PluginLoadError] = []
        self.distributions: dict[str, str] = {}
        self._backends: dict[str, dict[str, BackendInfo]] | None = None

    # ---- discovery --------------------------------------------------------------------------

    def load_entry_points(self, entry_points: Iterable[md.EntryPoint] | None = None) -> None:
        """Load every entry point of the ``dotshell`` group (or the ones given)."""
        eps = md.entry_points(group=GROUP) if entry_points is None else entry_points
        seen: set[str] = set()
        for ep in sorted(eps, key=lambda e: e.name):
            if ep.name in seen:
                continue
            seen.add(ep.name)
            dist = f"{ep.dist.name} {ep.dist.version}" if ep.dist else "unknown distribution"
            try:
                plugin = ep.load()
            except Exception as exc:  # any import-time failure of third-party code
                last = traceback.extract_tb(exc.__traceback__)[-1:] if exc.__traceback__ else []
                at = f" at {last[0].filename}:{last[0].lineno}" if last else ""
                self._load_failed(PluginLoadError(ep.name, dist, f"{type(exc).__name__}: {exc}{at}"))
                continue
            self.register(plugin, name=ep.name, distribution=dist)

    def register(self, plugin: Any, name: str, distribution: str = "local") -> None:
        """Register a plugin object or module directly (tests, scripts)."""
        try:
            self.pm.register(plugin, name=name)
        except Exception as exc:  # pluggy validation errors (bad hook names/signatures)
            self._load_failed(PluginLoadError(name, distribution, f"{type(exc).__name__}: {exc}"))
            return
        self.distributions[name] = distribution
        self._backends = None

    def _load_failed(self, err: PluginLoadError) -> None:
        if self.strict:
            raise PluginError(f"{err} (--strict-plugins makes plugin load failures fatal; fix or "
                              "uninstall the plugin, or run without --strict-plugins).")
        self.load_errors.append(err)

    # ---- backends ---------------------------------------------------------------------------

    def _collect(self) -> dict[str, dict[str, BackendInfo]]:
        table: dict[str, dict[str, BackendInfo]] = {role: {} for role in ROLES}
        for role, hook_name in ROLES.items():
            for impl in getattr(self.pm.hook, hook_name).get_hookimpls():
                dist = self.distributions.get(impl.plugin_name, "local")
                try:
                    provided = impl.function() or []
                except Exception as exc:
                    self._load_failed(PluginLoadError(
                        impl.plugin_name, dist, f"{hook_name}() raised {type(exc).__name__}: {exc}"))
                    continue
                for b in provided:
                    if b.name in table[role]:
                        other = table[role][b.name]
                        self._load_failed(PluginLoadError(
                            impl.plugin_name, dist, f"{role} backend {b.name!r} is already "
                            f"provided by plugin {other.plugin!r}; the first one is kept"))
                        continue
                    table[role][b.name] = BackendInfo(role, b, impl.plugin_name, dist)
        return table

    def backends(self, role: str) -> dict[str, BackendInfo]:
        """All backends for ``role`` by name."""
        if role not in ROLES:
            raise PluginError(f"unknown role {role!r}; roles are {', '.join(ROLES)}.")
        if self._backends is None:
            self._backends = self._collect()
        return self._backends[role]

    def backend(self, role: str, name: str, where: str = "profile") -> BackendInfo:
        """The backend ``name`` for ``role``, or a :class:`PluginError` listing the choices."""
        found = self.backends(role)
        if name in found:
            return found[name]
        choices = ", ".join(repr(n) for n in sorted(found)) or "(none installed)"
        hint = ""
        if self.load_errors:
            hint = " Some plugins failed to load and may have provided it: " + "; ".join(
                str(e) for e in self.load_errors) + "."
        raise PluginError(f"{where}: [{role}.backend] = {name!r} is not an installed {role} "
                          f"backend. Valid choices: {choices}.{hint} "
                          "Run `dotshell plugins` to see every backend.")

    def create(self, role: str, name: str, settings: Mapping[str, Any] | None,
               context: Any = None, where: str = "profile") -> Any:
        """Validate ``settings`` against the backend's schema and call its factory."""
        info = self.backend(role, name, where)
        clean = validate_settings(info.backend.settings_schema, settings, where, f"{role}.settings")
        return info.backend.factory(settings=clean, context=context)

    # ---- workflow hooks ---------------------------------------------------------------------

    def notify(self, hook_name: str, **kwargs: Any) -> list[str]:
        """Call a workflow hook on every plugin; return warnings for plugins that raised."""
        warnings = []
        for impl in getattr(self.pm.hook, hook_name).get_hookimpls():
            args = {k: v for k, v in kwargs.items() if k in impl.argnames}
            try:
                impl.function(**args)
            except Exception as exc:
                warnings.append(f"plugin {impl.plugin_name!r} failed in {hook_name}: "
                                f"{type(exc).__name__}: {exc}")
        return warnings


_default: PluginManager | None = None


def get_plugin_manager(strict: bool = False) -> PluginManager:
    """The process-wide plugin manager with all installed entry points loaded."""
    global _default
    if _default is None or (strict and not _default.strict):
        pm = PluginManager(strict=strict)
        pm.load_entry_points()
        _default = pm
    return _default
