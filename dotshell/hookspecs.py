"""The dotshell plugin contract — every hook a plugin may implement, in one place.

A plugin is a module (or object) registered under the ``dotshell`` entry-point group::

    [project.entry-points.dotshell]
    my_plugin = "my_package.plugin"

and implements any of the hooks below with :data:`dotshell.hookimpl`. Hooks are always called
with keyword arguments, so an implementation may accept only the arguments it needs.

**Backend hooks** return a list of :class:`dotshell.backends.Backend` for one role; the profile
chooses among all plugins' backends by name. A plugin that declares its backends in a
``dotshell.toml`` manifest instead (:mod:`dotshell.manifest`; all first-party plugins do) is not
imported until one of them is used; its package's hooks are then only for being registered as
a plain pluggy plugin.

**Workflow hooks** observe a scan; they must not raise (an exception is logged as a warning
against the plugin and the scan goes on) and should return quickly.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import pluggy

if TYPE_CHECKING:  # pragma: no cover
    from dotshell.backends import Backend

hookspec = pluggy.HookspecMarker("dotshell")

# ---- backends by role -------------------------------------------------------------------------


@hookspec
def dotshell_cameras() -> list[Backend]:
    """Camera backends. Factories return a :class:`dotshell.devices.Camera`."""


@hookspec
def dotshell_projectors() -> list[Backend]:
    """Projector backends. Factories return a :class:`dotshell.devices.Projector`."""


@hookspec
def dotshell_stages() -> list[Backend]:
    """Rotation-stage backends. Factories return a :class:`dotshell.devices.Stage`."""


@hookspec
def dotshell_analyzers() -> list[Backend]:
    """Polarization-analyzer backends. Factories return a :class:`dotshell.devices.Analyzer`."""


@hookspec
def dotshell_light_sources() -> list[Backend]:
    """Light-source backends (trans-illumination laser). Factories return a
    :class:`dotshell.devices.LightSource`."""


@hookspec
def dotshell_codings() -> list[Backend]:
    """Pattern codings. Factories return a :class:`dotshell.coding.PatternCoding`; they are
    called with ``context=None`` because codings touch no hardware."""


@hookspec
def dotshell_surface_meshers() -> list[Backend]:
    """Surface meshers: point cloud → closed triangle surface."""


@hookspec
def dotshell_volume_meshers() -> list[Backend]:
    """Volume meshers: closed surface → tetrahedral mesh."""


@hookspec
def dotshell_normalizers() -> list[Backend]:
    """Trans-illumination intensity normalization methods."""


@hookspec
def dotshell_exporters() -> list[Backend]:
    """Exporters. Factories return an object with ``export(run_dir: Path) -> list[Path]`` that
    reads the run's products (``cloud.ply``, meshes) and writes files under the run directory,
    returning the paths written."""


# ---- workflow events --------------------------------------------------------------------------


@hookspec
def dotshell_scan_started(run_dir: str, profile: dict[str, Any], n_views: int) -> None:
    """A scan began writing to ``run_dir``; ``profile`` is the validated profile."""


@hookspec
def dotshell_view_captured(run_dir: str, view: int, angle_deg: float, n_frames: int) -> None:
    """All frames of view ``view`` (0-based) at stage angle ``angle_deg`` are on disk."""


@hookspec
def dotshell_view_reconstructed(run_dir: str, view: int, n_points: int) -> None:
    """View ``view`` was decoded and triangulated into ``n_points`` sample-frame points."""


@hookspec
def dotshell_scan_finished(run_dir: str, status: str, report: dict[str, Any]) -> None:
    """The scan ended; ``status`` is ``"completed"``, ``"aborted"`` or ``"failed"``."""
