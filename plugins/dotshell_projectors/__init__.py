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

The backends are declared in ``dotshell.toml`` and built in :mod:`dotshell_projectors.backends`:
this module imports no driver.
"""

from __future__ import annotations

from dotshell import hookimpl
from dotshell.backends import Backend
from dotshell.manifest import backends_of


@hookimpl
def dotshell_projectors() -> list[Backend]:
    """All projectors, imported (when this package is registered as a plain pluggy plugin)."""
    return backends_of(__name__, "projector")
