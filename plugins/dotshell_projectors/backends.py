"""The projector backends, each built on first use (``python_name`` targets of this package's
``dotshell.toml``): importing this module imports no driver (nor pyusb, pyglet)."""

from __future__ import annotations

from typing import Any

from dotshell.backends import Backend, RigContext


def framebuffer() -> Backend:
    from dotshell_projectors.framebuffer import SETTINGS_SCHEMA, FramebufferProjector

    def make(settings: dict[str, Any], context: RigContext | None = None) -> FramebufferProjector:
        return FramebufferProjector(settings)

    return Backend("framebuffer", make, SETTINGS_SCHEMA)


def window() -> Backend:
    from dotshell_projectors.window import SETTINGS_SCHEMA, WindowProjector

    def make(settings: dict[str, Any], context: RigContext | None = None) -> WindowProjector:
        return WindowProjector(settings)

    return Backend("window", make, SETTINGS_SCHEMA)


def lightcrafter4500() -> Backend:
    from dotshell_projectors.lightcrafter import SETTINGS_SCHEMA, LightCrafter4500

    def make(settings: dict[str, Any], context: RigContext | None = None) -> LightCrafter4500:
        return LightCrafter4500(settings, context.base_dir if context else ".")

    return Backend("lightcrafter4500", make, SETTINGS_SCHEMA)


def _simulated(name: str) -> Backend:
    """A driver whose far end is the simulator (needs dotshell_sim)."""
    from dotshell_projectors.simulated import backends

    [(make, schema)] = [(make, schema) for n, make, schema, _ in backends() if n == name]
    return Backend(name, make, schema)


def lightcrafter4500_sim() -> Backend:
    return _simulated("lightcrafter4500-sim")


def framebuffer_sim() -> Backend:
    return _simulated("framebuffer-sim")
