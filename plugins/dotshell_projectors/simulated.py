"""Real projector drivers whose far end is the simulator: for tests, demos and benchmarks.

* ``lightcrafter4500-sim``: the LightCrafter 4500 driver (:mod:`.lightcrafter`) talking USB to
  the emulated controller (:mod:`.lc4500_emulator`), whose DMD lights the simulated scene through
  a sim projector's optics; its TRIG_OUT_1 edges reach the sim camera's trigger input.
* ``framebuffer-sim``: the framebuffer driver (:mod:`.framebuffer`) writing into a file-backed
  framebuffer; a scan-out reads that memory back (its own decoding of the pixel layout) and the
  sim projector's optics put it on the scene after the display latency.

Only the far end is simulated: the driver code under test is the code a lab runs. Settings are
the driver's plus the optics of ``sim-projector`` (pose, lens, brightness, time model); the
panel size is the device's (912 × 1140 for the DLP4500, the framebuffer's geometry).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from dotshell.backends import RigContext
from dotshell.settings import Setting, validate_settings
from dotshell_projectors import dlpc350
from dotshell_projectors.framebuffer import BYTES, FramebufferProjector, decode
from dotshell_projectors.framebuffer import SETTINGS_SCHEMA as FB_SCHEMA
from dotshell_projectors.lc4500_emulator import EmulatedLightCrafter
from dotshell_projectors.lc4500_images import load
from dotshell_projectors.lightcrafter import SETTINGS_SCHEMA as LC_SCHEMA
from dotshell_projectors.lightcrafter import LightCrafter4500


def optics_schema() -> dict[str, Setting]:
    """The sim projector's settings without its panel size."""
    from dotshell_sim.devices import PROJECTOR_SCHEMA

    return {k: v for k, v in PROJECTOR_SCHEMA.items() if k not in ("width", "height")}


def _optics(settings: dict[str, Any], size: tuple[int, int], context: RigContext | None):
    from dotshell_sim.devices import make_projector

    keys = optics_schema()
    given = {k: v for k, v in settings.items() if k in keys}
    return make_projector(settings={**given, "width": size[0], "height": size[1]},
                          context=context)


class SimDisplay:
    """The emulated DMD's light, put on the sim projector's display timeline."""

    def __init__(self, optics: Any) -> None:
        self.optics = optics

    def now(self) -> float:
        return self.optics.clock.now()

    def run(self, images: list[np.ndarray], exposure_s: float, period_s: float) -> None:
        self.optics.timeline.run_sequence(self.now(), [(im, "", -1) for im in images],
                                          exposure_s, period_s)

    def show(self, image: np.ndarray) -> None:
        self.optics.timeline.show(self.now(), image)

    def stop(self) -> None:
        self.optics.timeline.stop(self.now())


class SimulatedLightCrafter(LightCrafter4500):
    """The LightCrafter driver on the emulator; ``emulator`` holds the fault switches."""

    def __init__(self, settings: dict[str, Any], context: RigContext | None) -> None:
        base = context.base_dir if context is not None else "."
        self.optics = _optics(settings, (dlpc350.WIDTH, dlpc350.HEIGHT), context)
        paths = [p if Path(p).is_absolute() else str(Path(base) / p)
                 for p in settings["flash_images"]]
        self.emulator = EmulatedLightCrafter(load(paths), display=SimDisplay(self.optics))
        super().__init__(settings, base, backend=self.emulator)

    def connect(self) -> None:
        self.optics.connect()
        super().connect()

    def close(self) -> None:
        super().close()
        self.optics.close()


class SimulatedFramebuffer(FramebufferProjector):
    """The framebuffer driver on a file; the scan-out shows the file's pixels on the scene."""

    def __init__(self, settings: dict[str, Any], context: RigContext | None) -> None:
        super().__init__(settings)
        self.optics = _optics(settings, self.resolution, context)

    def connect(self) -> None:
        self.optics.connect()
        super().connect()

    def close(self) -> None:
        super().close()
        self.optics.close()

    def show(self, pattern: np.ndarray, name: str = "", index: int = -1) -> None:
        super().show(pattern, name, index)
        self._scan_out()

    def _scan_out(self) -> None:
        """Read the visible screen from the framebuffer file and put it on the panel."""
        from dotshell_sim.timing import display_time

        g = self.geometry
        raw = np.fromfile(self.device, np.uint8, g.stride * g.height).reshape(g.height, g.stride)
        n = BYTES[g.layout]
        gray = decode(raw[:, :g.width * n].reshape(g.height, g.width, n), g.layout)
        s = self.optics.settings
        at = display_time(self.optics.clock.now(), s["display_latency_ms"], s["refresh_hz"])
        self.optics.timeline.show(at, gray)


def _factory(cls, schema: dict[str, Setting], name: str):
    def make(settings: dict | None = None, context: RigContext | None = None):
        given = {k: v for k, v in (settings or {}).items() if v is not None}
        return cls(validate_settings(schema, given, name), context)

    return make


def backends() -> list[tuple[str, Any, dict[str, Setting], str]]:
    """(name, factory, schema, summary) of the simulator-coupled backends."""
    lc = {**LC_SCHEMA, **optics_schema()}
    lc["pixel_aspect"] = Setting("float", 0.5, lc["pixel_aspect"].help, min=0.1, max=10.0)
    fb = {**FB_SCHEMA, **optics_schema()}
    return [
        ("lightcrafter4500-sim", _factory(SimulatedLightCrafter, lc, "lightcrafter4500-sim"), lc,
         "LightCrafter 4500 driver on its USB emulator lighting the simulated scene"),
        ("framebuffer-sim", _factory(SimulatedFramebuffer, fb, "framebuffer-sim"), fb,
         "framebuffer driver on a file-backed framebuffer scanned out onto the simulated scene"),
    ]
