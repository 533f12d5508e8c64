"""Plugin discovery: entry points of the ``dotshell`` group, loaded one by one.

A plugin whose package ships a ``dotshell.toml`` manifest (:mod:`dotshell.manifest`) is not
imported: its backends are known from the manifest and each is imported the first time it is
used (:attr:`BackendInfo.backend`). A plugin without one is imported here and asked for its
backends through the hooks of :mod:`dotshell.hookspecs`.

A plugin that fails to import is recorded in :attr:`PluginManager.load_errors` with its name,
distribution and reason; the others still load. ``strict=True`` (``--strict-plugins``) turns
such a failure into a :class:`~dotshell.errors.PluginError` — for plugin authors and CI.
"""

from __future__ import annotations

import importlib
import importlib.metadata as md
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Iterable, Mapping

import pluggy

from dotshell import hookspecs
from dotshell.backends import ROLES, Backend
from dotshell.errors import DotshellError, PluginError, PluginFault
from dotshell.manifest import (Manifest, ManifestBackend, find_manifest, raised_at, read_manifest,
                               short_repr)
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


class BackendInfo:
    """A backend together with the plugin and distribution that provide it. Its role, name,
    summary and USB ids are known without importing anything; :attr:`backend` imports a
    backend declared in a manifest the first time it is asked for (and keeps it)."""

    def __init__(self, role: str, plugin: str, distribution: str, name: str, summary: str = "",
                 usb_ids: tuple[str, ...] = (), backend: Backend | None = None,
                 declared: ManifestBackend | None = None) -> None:
        self.role = role
        self.plugin = plugin
        self.distribution = distribution
        self.name = name
        self.summary = summary
        self.usb_ids = usb_ids
        self._backend = backend
        self._declared = declared

    @classmethod
    def of(cls, role: str, backend: Backend, plugin: str, distribution: str) -> BackendInfo:
        """A backend a plugin's hook returned (already imported)."""
        return cls(role, plugin, distribution, backend.name, backend.summary, backend.usb_ids,
                   backend=backend)

    @classmethod
    def from_manifest(cls, entry: ManifestBackend, plugin: str,
                      distribution: str) -> BackendInfo:
        """A backend a plugin's manifest declares (imported on first use)."""
        return cls(entry.kind, plugin, distribution, entry.name, entry.summary, entry.usb_ids,
                   declared=entry)

    @property
    def loaded(self) -> bool:
        """Whether the backend's module has been imported."""
        return self._backend is not None

    @property
    def backend(self) -> Backend:
        """The :class:`Backend`, imported on first use; :class:`PluginError` naming the plugin,
        the backend and the import's error when its module is broken."""
        if self._backend is None:
            assert self._declared is not None
            try:
                self._backend = self._declared.load()
            except PluginError as exc:
                raise PluginError(f"plugin {self.plugin!r} ({self.distribution}) failed to load "
                                  f"its {self.role} backend {self.name!r}: {exc}. Fix or "
                                  "reinstall the plugin, or choose another backend in the "
                                  "profile (`dotshell plugins --check` loads every backend)."
                                  ) from exc
        return self._backend

    def __repr__(self) -> str:
        return (f"BackendInfo({self.role!r}, {self.name!r}, plugin={self.plugin!r}, "
                f"loaded={self.loaded})")


class PluginManager:
    """Finds plugins and the backends they provide, by role and name."""

    def __init__(self, strict: bool = False) -> None:
        self.strict = strict
        self.pm = pluggy.PluginManager("dotshell")
        self.pm.add_hookspecs(hookspecs)
        self.load_errors: list[PluginLoadError] = []
        self.distributions: dict[str, str] = {}
        #: plugins found with a manifest (dotshell.toml): their backends are imported on use
        self.manifests: dict[str, Manifest] = {}
        self._backends: dict[str, dict[str, BackendInfo]] | None = None
        self.qualified: dict[str, dict[str, BackendInfo]] = {}
        #: seconds a workflow hook may take before the workflow goes on without it
        self.hook_timeout_s = HOOK_TIMEOUT_S

    # ---- discovery --------------------------------------------------------------------------

    def load_entry_points(self, entry_points: Iterable[md.EntryPoint] | None = None) -> None:
        """Load every entry point of the ``dotshell`` group (or the ones given), first-party
        ones first, then collect every plugin's backends at once, so load errors —
        duplicate backend names, entry-point names that shadow dotshell's own — are known to
        every command at start-up."""
        eps = md.entry_points(group=GROUP) if entry_points is None else entry_points
        named = [(ep, *distribution_of(ep)) for ep in eps]
        seen: dict[str, str] = {}
        for ep, dist_name, dist in sorted(named, key=lambda e: (e[1] != "dotshell", e[0].name)):
            name = ep.name
            if name in seen:
                if seen[name] == dist:
                    continue  # the same distribution seen twice on sys.path
                name = f"{ep.name}@{dist_name or 'unknown'}"
                self._load_failed(PluginLoadError(
                    ep.name, dist, f"its entry-point name {ep.name!r} is already taken by "
                    f"{seen[ep.name]}; it is loaded as {name!r} (rename the entry point in the "
                    "plugin's pyproject.toml)"))
            seen.setdefault(ep.name, dist)
            if self._load_manifest(ep, name, dist):
                continue
            try:
                plugin = ep.load()
            except BaseException as exc:  # any import-time failure, sys.exit() included
                if _user_interrupt(exc):
                    raise
                self._load_failed(PluginLoadError(ep.name, dist,
                                                  f"{type(exc).__name__}: {exc}{raised_at(exc)}"))
                continue
            self.register(plugin, name=name, distribution=dist)
        self.backends("camera")  # collect now: duplicate or malformed backends are load errors
        if self.strict:  # plugin authors and CI: every declared backend must import
            for failure in self.check_backends():
                self._load_failed(failure)

    def _load_manifest(self, ep: md.EntryPoint, name: str, dist: str) -> bool:
        """Take the plugin's backends from its manifest when it has one (nothing of the plugin
        is imported, except a workflow-hook module it names); False when it has none."""
        path = find_manifest(ep.module)
        if path is None:
            return False
        try:
            manifest = read_manifest(path)
        except PluginError as exc:
            self._load_failed(PluginLoadError(ep.name, dist, str(exc)))
            return True
        self.manifests[name] = manifest
        self.distributions[name] = dist
        self._backends = None
        if manifest.hooks:
            try:
                module = importlib.import_module(manifest.hooks)
            except (Exception, SystemExit) as exc:  # plugin code: any import-time failure
                self._load_failed(PluginLoadError(
                    ep.name, dist, f"its hooks module {manifest.hooks!r} raised "
                    f"{type(exc).__name__}: {exc}{raised_at(exc)}"))
                return True
            self.register(module, name=name, distribution=dist)
        return True

    def check_backends(self) -> list[PluginLoadError]:
        """Import every backend declared in a manifest; one error per backend that fails."""
        failures = []
        for role in ROLES:
            self.backends(role)
            for info in self.qualified[role].values():  # duplicates kept aside included
                try:
                    _ = info.backend  # imports it
                except PluginError as exc:
                    failures.append(PluginLoadError(info.plugin, info.distribution, str(exc)))
        return failures

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
        self.qualified = {role: {} for role in ROLES}
        for role, hook_name in ROLES.items():
            impls = {i.plugin_name: i for i in getattr(self.pm.hook, hook_name).get_hookimpls()}
            # first-party plugins first, then in the order they were loaded or registered
            plugins = [*self.distributions, *(p for p in impls if p not in self.distributions)]
            for plugin in sorted(plugins, key=self._order):
                for info in self._infos(plugin, role, impls.get(plugin)):
                    self._enter(table[role], info)
        return table

    def _infos(self, plugin: str, role: str, impl: Any) -> list[BackendInfo]:
        """One plugin's ``role`` backends: declared in its manifest, then from its hook."""
        dist = self.distributions.get(plugin, "local")
        manifest = self.manifests.get(plugin)
        infos = [BackendInfo.from_manifest(b, plugin, dist)
                 for b in (manifest.of_kind(role) if manifest else [])]
        if impl is not None:
            infos += [BackendInfo.of(role, b, plugin, dist)
                      for b in self._provided(impl, ROLES[role], dist)]
        return infos

    def _enter(self, table: dict[str, BackendInfo], info: BackendInfo) -> None:
        """Add a backend under its name (and ``plugin:name``); a second one of the same name is
        a load error of its plugin."""
        self.qualified[info.role][f"{info.plugin}:{info.name}"] = info
        if info.name in table:
            other = table[info.name]
            self._load_failed(PluginLoadError(
                info.plugin, info.distribution, f"{info.role} backend {info.name!r} is already "
                f"provided by plugin {other.plugin!r} ({other.distribution}), which is kept; "
                f"choose this one with backend = \"{info.plugin}:{info.name}\""))
            return
        table[info.name] = info

    def _order(self, plugin_name: str) -> tuple[bool, int]:
        dist = self.distributions.get(plugin_name, "local")
        names = list(self.distributions)
        return (not dist.startswith("dotshell "),
                names.index(plugin_name) if plugin_name in names else len(names))

    def _provided(self, impl: Any, hook_name: str, dist: str) -> list[Backend]:
        """What one plugin's backend hook returned, checked; a fault is that plugin's load
        error."""
        try:
            provided = impl.function()
        except BaseException as exc:  # noqa: BLE001 - plugin code: contain everything
            if _user_interrupt(exc):
                raise
            self._load_failed(PluginLoadError(
                impl.plugin_name, dist, f"{hook_name}() raised {type(exc).__name__}: {exc}"))
            return []
        if provided is None:
            return []
        if not isinstance(provided, (list, tuple)) or not all(
                isinstance(b, Backend) and isinstance(b.name, str) and b.name and callable(b.factory)
                and _schema_ok(b.settings_schema) for b in provided):
            self._load_failed(PluginLoadError(
                impl.plugin_name, dist, f"{hook_name}() must return a list of "
                "dotshell.backends.Backend (a name, a callable factory and a settings schema of "
                f"dotshell.settings.Setting); it returned {short_repr(provided)}"))
            return []
        return list(provided)

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
        if ":" in name and name in self.qualified.get(role, {}):  # plugin:backend
            return self.qualified[role][name]
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
        try:
            obj = info.backend.factory(settings=clean, context=context)
        except (DotshellError, MemoryError):
            raise
        except Exception as exc:  # plugin code: name it, never a traceback
            raise PluginFault(plugin_fault(info, "creating the device" if role in DEVICE_ROLES
                                           else f"creating the {role}", exc)) from exc
        return obj if role in DEVICE_ROLES else PluginObject(obj, info)

    # ---- workflow hooks ---------------------------------------------------------------------

    def notify(self, hook_name: str, **kwargs: Any) -> list[str]:
        """Call a workflow hook on every plugin; return warnings for plugins that raised."""
        warnings = []
        for impl in getattr(self.pm.hook, hook_name).get_hookimpls():
            args = {k: v for k, v in kwargs.items() if k in impl.argnames}
            failure = _call_with_timeout(impl.function, args, self.hook_timeout_s)
            if failure:
                warnings.append(f"plugin {impl.plugin_name!r} {failure} in {hook_name}; the "
                                "workflow went on without it")
        return warnings


HOOK_TIMEOUT_S = 10.0
DEVICE_ROLES = ("camera", "projector", "stage", "analyzer", "light_source")


def distribution_of(ep: md.EntryPoint) -> tuple[str, str]:
    """(name, "name version") of the distribution that provides ``ep`` ("" and "unknown
    distribution" when none does). The METADATA is parsed once per distribution object:
    ``dist.name`` and ``dist.version`` parse the whole file each time (about 2 ms; it was done
    three times per entry point at every start)."""
    return ("", "unknown distribution") if ep.dist is None else _distribution_label(ep.dist)


@lru_cache(maxsize=32)  # the entry points of one distribution share its object
def _distribution_label(dist: md.Distribution) -> tuple[str, str]:
    meta = dist.metadata
    return meta["Name"], f"{meta['Name']} {meta['Version']}"


def _user_interrupt(exc: BaseException) -> bool:
    """A real Ctrl-C / stop signal (to be obeyed), not a plugin raising KeyboardInterrupt."""
    from dotshell.errors import Interrupted

    return isinstance(exc, Interrupted)


def _schema_ok(schema: Any) -> bool:
    from dotshell.settings import Setting

    return isinstance(schema, Mapping) and all(
        isinstance(k, str) and isinstance(v, Setting) for k, v in schema.items())


class PluginObject:
    """A coding, mesher, normalizer or exporter as the pipeline uses it: every method call
    that raises something other than a :class:`DotshellError` (or ``MemoryError``) becomes a
    :class:`PluginFault` naming the plugin, role, backend and method. (Devices get the same
    from the rig.) Attributes and ``isinstance`` checks against protocols pass through."""

    def __init__(self, obj: Any, info: BackendInfo) -> None:
        object.__setattr__(self, "_obj", obj)
        object.__setattr__(self, "_info", info)

    def __getattr__(self, name: str) -> Any:
        value = getattr(self._obj, name)
        if not callable(value):
            return value
        info = self._info

        def call(*args: Any, **kwargs: Any) -> Any:
            try:
                return value(*args, **kwargs)
            except (DotshellError, MemoryError):
                raise
            except Exception as exc:  # plugin code: name it, never a traceback
                raise PluginFault(plugin_fault(info, f"{name}()", exc)) from exc

        return call

    def __setattr__(self, name: str, value: Any) -> None:
        setattr(self._obj, name, value)

    def __repr__(self) -> str:
        return repr(self._obj)

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickled (into the mesh process, :mod:`dotshell.pipeline.mesh_process`) as the
        plugin's object and the names a fault message needs; the backend itself (its factory
        is often a local function) stays behind."""
        i = self._info
        return (PluginObject, (self._obj, BackendInfo(i.role, i.plugin, i.distribution, i.name,
                                                      i.summary, i.usb_ids)))


def plugin_fault(info: BackendInfo, doing: str, exc: BaseException) -> str:
    """The one-paragraph message for plugin code that raised something unexpected."""
    return (f"plugin {info.plugin!r} ({info.distribution}; role {info.role}, backend "
            f"{info.name!r}) raised {type(exc).__name__} while {doing}: {exc}. This is a "
            "fault of the plugin: update or fix it, or choose another backend in the profile.")


def _call_with_timeout(fn: Any, kwargs: dict[str, Any], timeout_s: float) -> str:
    """Run a workflow hook on a helper thread; '' if it returned in time, else what went
    wrong ('raised X: ...', 'did not return within N s')."""
    import threading

    result: list[str] = []

    def target() -> None:
        try:
            fn(**kwargs)
            result.append("")
        except BaseException as exc:  # noqa: BLE001 - plugin code
            result.append(f"raised {type(exc).__name__}: {exc}")

    t = threading.Thread(target=target, name="dotshell-hook", daemon=True)
    t.start()
    t.join(timeout_s)
    if t.is_alive():
        return f"did not return within {timeout_s:g} s"
    return result[0]


_default: PluginManager | None = None


def get_plugin_manager(strict: bool = False) -> PluginManager:
    """The process-wide plugin manager with all installed entry points loaded."""
    global _default
    if _default is None or (strict and not _default.strict):
        pm = PluginManager(strict=strict)
        pm.load_entry_points()
        _default = pm
    return _default


#: The entry-point group of device emulators (``dotshell emulate NAME``, docs/devices.md).
EMULATOR_GROUP = "dotshell_emulators"


def emulator_class(name: str) -> type:
    """The emulator registered as ``name`` in the ``dotshell_emulators`` entry-point group."""
    eps = {ep.name: ep for ep in md.entry_points(group=EMULATOR_GROUP)}
    if name not in eps:
        raise PluginError(f"no emulator named {name!r}; installed emulators: "
                          f"{', '.join(sorted(eps)) or '(none)'}.")
    try:
        return eps[name].load()
    except Exception as exc:
        raise PluginError(f"emulator {name!r} ({eps[name].value}) failed to load: "
                          f"{type(exc).__name__}: {exc}") from None
