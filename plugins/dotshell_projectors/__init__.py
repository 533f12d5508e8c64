"""dotshell_projectors — real projectors: Linux framebuffer, a fullscreen window, the TI DLP
LightCrafter 4500 over USB (and its emulator).

Registered under the ``dotshell`` entry-point group as ``projectors = "dotshell_projectors"``.
Backends (docs/hardware.md):

* ``framebuffer`` — a second screen through ``/dev/fbN`` (no desktop needed);
* ``window`` — a fullscreen window on a named screen (optional extra ``dotshell[window]``);
* ``lightcrafter4500`` — DLPC350 pattern mode over USB HID with pyusb: stored pattern
  sequences, exposure and period, TRIG_OUT_1 to the camera, status and error registers;
* ``lightcrafter4500-sim``, ``framebuffer-sim`` — the same drivers with the simulator as their
  far end (an emulated controller, a file-backed framebuffer), for tests and benchmarks.
"""

from __future__ import annotations

from typing import Any

from dotshell import hookimpl
from dotshell.backends import Backend, RigContext
from dotshell_projectors.framebuffer import SETTINGS_SCHEMA as FRAMEBUFFER_SCHEMA
from dotshell_projectors.framebuffer import FramebufferProjector
from dotshell_projectors.lightcrafter import SETTINGS_SCHEMA as LIGHTCRAFTER_SCHEMA
from dotshell_projectors.lightcrafter import LightCrafter4500
from dotshell_projectors.window import SETTINGS_SCHEMA as WINDOW_SCHEMA
from dotshell_projectors.window import WindowProjector


def _framebuffer(settings: dict[str, Any], context: RigContext) -> FramebufferProjector:
    return FramebufferProjector(settings)


def _window(settings: dict[str, Any], context: RigContext) -> WindowProjector:
    return WindowProjector(settings)


def _lightcrafter(settings: dict[str, Any], context: RigContext) -> LightCrafter4500:
    return LightCrafter4500(settings, context.base_dir if context else ".")


@hookimpl
def dotshell_projectors() -> list[Backend]:
    out = [
        Backend("framebuffer", _framebuffer, FRAMEBUFFER_SCHEMA,
                "second screen through the Linux framebuffer /dev/fbN (sysfs geometry, mmap)"),
        Backend("window", _window, WINDOW_SCHEMA,
                "fullscreen window on a named screen with vsync (extra dotshell[window]: pyglet)"),
        Backend("lightcrafter4500", _lightcrafter, LIGHTCRAFTER_SCHEMA,
                "TI DLP LightCrafter 4500 (DLPC350) over USB HID: stored pattern sequences, "
                "trigger out to the camera"),
    ]
    try:
        from dotshell_projectors.simulated import backends
    except ImportError:  # the simulator is not installed
        return out
    return out + [Backend(name, make, schema, summary)
                  for name, make, schema, summary in backends()]
