"""Simulated devices sharing one world per rig (``context.shared["dotshell_sim"]``).

The projector stores the shown pattern, the turntable its angle, the analyzer its angle, the
laser its state; the camera renders the world on ``capture()`` (see :mod:`dotshell_sim.render`).

The default settings describe the reference bench (also written out, with comments, in
``profiles/sim-metal-cylinder.toml``). All poses are in the **bench frame**, which is the
camera's frame at its default pose (mm; x right, y down, z along the camera's optical axis); a
camera placed elsewhere (``position_mm``, ``look_at_mm``, ``up``: a rig's second camera) sees
the projector and the turntable moved into its own frame:

* camera 1280×1024, 5.3 µm pixels, f ≈ 33.9 mm (fx = 6400 px) → 40 × 32 mm field at 200 mm;
  12 bit, full well 10 000 e-, read noise 10 e-; k1 = -0.08.
* the camera looks down by 15°: the turntable axis (world vertical) is
  ``(0, -cos 15°, -sin 15°)`` in the camera frame and crosses the optical axis 200 mm in front
  of the camera; the stage plate is 16 mm below that point along the axis.
* projector 1024×768, fx = 4480 px → 48 × 36 mm field at 210 mm; its centre is at
  (80.9, -4.4, 6.3) mm, 210 mm from the crossing point (0, 0, 200) it looks at: a horizontal
  baseline of ~81 mm and a triangulation angle of 22.7° at the crossing point; k1 = -0.06.
"""

from __future__ import annotations

import json
import math
from collections import OrderedDict
from typing import Any

import cv2
import numpy as np

from dotshell.backends import RigContext
from dotshell.devices import FrameInfo, SequencePattern, SurfaceRadiance
from dotshell.errors import DeviceError, DeviceTimeout
from dotshell.geometry.calibration import RigCalibration
from dotshell.geometry.lens import Lens, lens_from_fov
from dotshell.settings import Setting, validate_settings

from dotshell.fem.optics import exit_radiance_per_fluence

from dotshell_sim import transillum
from dotshell_sim.timing import DisplayTimeline, SimClock, display_time
from dotshell_sim.lru import cached
from dotshell_sim.render import SMALL_VIEWS_BYTES, Light, Renderer, SensorModel, sensor
from dotshell_sim.scene import MATERIALS, build_scene

WORLD_KEY = "dotshell_sim"

_TILT = math.radians(15.0)
#: Reference bench: turntable axis (world up) and the plate point on it, camera frame.
BENCH_AXIS_DIRECTION = [0.0, round(-math.cos(_TILT), 6), round(-math.sin(_TILT), 6)]
BENCH_AXIS_POINT = [0.0, round(16 * math.cos(_TILT), 3), round(200 + 16 * math.sin(_TILT), 3)]

# ---- settings schemas -----------------------------------------------------------------------

CAMERA_SCHEMA: dict[str, Setting] = {
    "width": Setting("int", 1280, "sensor width", "px", min=8),
    "height": Setting("int", 1024, "sensor height", "px", min=8),
    "focal_px": Setting("float", 6400.0, "focal length in pixels (fx = fy); 6400 px = 33.9 mm "
                        "with 5.3 µm pixels, a 40 mm wide field at 200 mm", "px", min=1.0),
    "cx": Setting("float", None, "principal point x; omit for the image centre", "px"),
    "cy": Setting("float", None, "principal point y; omit for the image centre", "px"),
    "dist": Setting("list[float]", [-0.08, 0.12, 0.0, 0.0, 0.0],
                    "distortion k1, k2, p1, p2, k3 (OpenCV order)", length=5),
    "bit_depth": Setting("int", 12, "ADC bits: 8 → uint8 frames, 12 → uint16 frames 0..4095",
                         "bit", choices=(8, 12)),
    "full_well_e": Setting("float", 10000.0, "full-well capacity", "e-", min=1.0),
    "read_noise_e": Setting("float", 10.0, "read noise", "e- rms", min=0.0),
    "gain_dn_per_e": Setting("float", 0.0, "conversion gain; 0 = full well maps to full scale",
                             "DN/e-", min=0.0),
    "dark_offset_dn": Setting("float", 8.0, "black level added by the ADC", "DN", min=0.0),
    "sensitivity_e_per_ms": Setting(
        "float", 800.0, "electrons per ms from a white Lambertian surface facing a full-white "
        "projector at its reference distance (lens aperture, QE, projector power in one number)",
        "e-/ms", min=0.0),
    "exposure_ms": Setting("float", 20.0, "exposure until set_exposure() is called", "ms",
                           min=0.0),
    "ambient": Setting("float", 0.01, "room light relative to full projector light", min=0.0),
    "defocus_sigma_px": Setting("float", 0.5, "camera defocus (Gaussian sigma); 0 = sharp",
                                "px", min=0.0),
    # the camera's pose in the bench frame (the frame every other pose of the profile is given
    # in); the defaults put it at the bench frame's origin, looking along its z, y down
    "position_mm": Setting("list[float]", [0.0, 0.0, 0.0], "centre of projection in the bench "
                           "frame (where the projector and turntable poses are given); a "
                           "second camera of a rig sits away from the origin", "mm", length=3),
    "look_at_mm": Setting("list[float]", [0.0, 0.0, 200.0], "point on the optical axis, bench "
                          "frame", "mm", length=3),
    "up": Setting("list[float]", [0.0, -1.0, 0.0], "bench-frame direction that appears as "
                  "'up' (row 0 side) in the image; fixes the roll", length=3),
    "supersample": Setting("int", 2, "sub-pixel rays per pixel along each axis (pixel-area "
                           "integration)", min=1, max=4),
    "seed": Setting("int", 0, "noise seed; each frame's noise is drawn from this seed and the "
                   "rig's state when it is taken (pattern, angles, exposure)", min=0),
    "vignetting": Setting("float", 0.0, "extra lens vignetting: relative light loss at the image "
                          "corner, falling off as 1 − v·(r/r_corner)² from the principal point "
                          "(on top of the natural cos⁴); applies to all light, flat fields "
                          "included; 0 = none", min=0.0, max=0.99),
    # time model (dotshell_sim.timing)
    "readout_ms": Setting("float", 0.0, "time model: sensor readout and transfer after each "
                          "exposure; a capture() takes exposure + readout", "ms", min=0.0),
    "overlap_readout": Setting("bool", True, "time model: a triggered exposure may start while "
                               "the previous frame is read out (global-shutter overlap), so "
                               "triggers may come every max(exposure, readout) instead of "
                               "every exposure + readout"),
}

PROJECTOR_SCHEMA: dict[str, Setting] = {
    "width": Setting("int", 1024, "panel width", "px", min=8),
    "height": Setting("int", 768, "panel height", "px", min=8),
    "focal_px": Setting("float", 4480.0, "focal length in pixels; 4480 px gives a 48 mm wide "
                        "field at 210 mm", "px", min=1.0),
    "cx": Setting("float", None, "principal point x; omit for the panel centre", "px"),
    "cy": Setting("float", None, "principal point y; omit for the panel centre", "px"),
    "dist": Setting("list[float]", [-0.06, 0.08, 0.0, 0.0, 0.0],
                    "distortion k1, k2, p1, p2, k3 (OpenCV order)", length=5),
    "position_mm": Setting("list[float]", [80.9, -4.4, 6.3],
                           "projector centre of projection in the camera frame", "mm", length=3),
    "look_at_mm": Setting("list[float]", [0.0, 0.0, 200.0],
                          "point on the projector's optical axis, camera frame", "mm", length=3),
    "up": Setting("list[float]", list(BENCH_AXIS_DIRECTION),
                  "direction (camera frame) that appears as 'up' (row 0 side) in the "
                  "projector image; fixes the roll", length=3),
    "brightness": Setting("float", 1.0, "radiance of full white relative to the reference",
                          min=0.0),
    "black_level": Setting("float", 0.002, "light emitted for pattern value 0, relative to 255 "
                           "(finite contrast)", min=0.0, max=1.0),
    "defocus_sigma_px": Setting("float", 0.6, "projector defocus (Gaussian sigma on the panel)",
                                "px", min=0.0),
    "pixel_aspect": Setting("float", 1.0, "panel pixel height / width (fy = fx · aspect); 0.5 "
                            "for the diamond-pixel DLP4500 of a LightCrafter 4500 addressed as "
                            "912 × 1140", min=0.1, max=10.0),
    # time model (dotshell_sim.timing)
    "display_latency_ms": Setting("float", 0.0, "time model: from show() to the new image on "
                                  "the panel (video input lag, frame buffering); the runner's "
                                  "settle_ms must cover it", "ms", min=0.0),
    "refresh_hz": Setting("float", 0.0, "time model: panel refresh rate; a shown image appears "
                          "at the next refresh after the latency (0 = at once)", "Hz", min=0.0),
}

_SCENE_SCHEMA = {
    "kind": Setting("str", "cylinder", "sample shape; mouse and gummy-bear are fixed-size "
                    "mesh phantoms (dotshell_sim.phantoms)",
                    choices=("cylinder", "none", "mouse", "gummy-bear")),
    "radius_mm": Setting("float", 7.7, "cylinder radius", "mm", min=0.01),
    "height_mm": Setting("float", 30.0, "cylinder height above the plate", "mm", min=0.01),
    "offset_mm": Setting("list[float]", [0.0, 0.0], "cylinder axis offset from the turntable "
                         "axis (sample-frame x, y)", "mm", length=2),
    "material": Setting("str", "metal", "sample material", choices=tuple(MATERIALS)),
    # trans-illumination (sim-laser) of an opaque-looking sample; turbid materials (agar,
    # gummy) bring their own optics and must not set these
    "mua_per_mm": Setting("float", None, "absorption coefficient μa of the sample for "
                          "trans-illumination (sim-laser), when its material is opaque; "
                          "omit for turbid materials", "1/mm", min=0.0),
    "musp_per_mm": Setting("float", None, "reduced scattering coefficient μs' of the sample for "
                           "trans-illumination (sim-laser), when its material is opaque", "1/mm",
                           min=1e-3),
    "refractive_index": Setting("float", None, "refractive index of the sample for "
                                "trans-illumination with mua_per_mm / musp_per_mm; omit for "
                                "1.37 (soft tissue)", min=1.0, max=3.0),
}
_PLATE_SCHEMA = {
    "radius_mm": Setting("float", 30.0, "stage plate radius; 0 = no plate", "mm", min=0.0),
    "material": Setting("str", "plate", "plate material", choices=tuple(MATERIALS)),
}
_BACKGROUND_SCHEMA = {
    "distance_mm": Setting("float", 80.0, "background plane distance behind the turntable "
                           "axis; 0 = none (black)", "mm", min=0.0),
    "material": Setting("str", "background", "background material", choices=tuple(MATERIALS)),
}

TURNTABLE_SCHEMA: dict[str, Setting] = {
    "axis_point_mm": Setting("list[float]", list(BENCH_AXIS_POINT),
                             "point of the rotation axis at the plate surface, camera frame",
                             "mm", length=3),
    "axis_direction": Setting("list[float]", list(BENCH_AXIS_DIRECTION),
                              "rotation axis direction (plate → sample), camera frame", length=3),
    "steps_per_degree": Setting("float", 0.0, "motor resolution; angles are rounded to whole "
                                "steps (0 = continuous)", "1/deg", min=0.0),
    "scene": Setting("table", {}, "the sample on the plate", schema=_SCENE_SCHEMA),
    "plate": Setting("table", {}, "stage plate (disk at sample z = 0)", schema=_PLATE_SCHEMA),
    "background": Setting("table", {}, "dark plane behind the sample (fixed, does not turn)",
                          schema=_BACKGROUND_SCHEMA),
}

CAMERA_SCHEMA["turntable"] = Setting(
    "table", None, "mixed rigs: the sample, plate and rotation axis the camera sees when the "
    "rig's [stage] is a real stage (e.g. on its emulator) instead of sim-turntable; the sample "
    "turns to the angle that stage reports (read back)", schema=TURNTABLE_SCHEMA)

ANALYZER_SCHEMA: dict[str, Setting] = {
    "initial_deg": Setting("float", 0.0, "analyzer angle after connect, relative to the "
                           "projector's polarizer (0 = parallel)", "deg"),
    "extinction_ratio": Setting("float", 1000.0, "crossed-polarizer extinction (max / min "
                                "transmission of polarized light); 1000 for a good film "
                                "polarizer", min=1.0),
    "transmittance": Setting("float", 0.85, "transmission of polarized light along the "
                             "analyzer axis", min=0.0, max=1.0),
}

CAMERA_SCHEMA["analyzer"] = Setting(
    "table", None, "mixed rigs: the analyzer optics in front of the camera when the rig's "
    "[analyzer] is a real rotation mount (e.g. elliptec on its emulator) instead of "
    "sim-analyzer; the optics turn to the angle that mount reports", schema=ANALYZER_SCHEMA)

LASER_SCHEMA: dict[str, Setting] = {
    "wavelength_nm": Setting("float", 780.0, "for the record only (the sample's optics are "
                             "given for the laser's wavelength)", "nm", min=0.0),
    "power": Setting("float", 4.0e4, "beam power in the renderer's relative units: light leaves "
                     "the sample with radiance power · φ · L(θo)/φ (φ per unit power, 1/mm²; "
                     "1 = a white Lambertian surface under full projector light); 4e4 peaks at "
                     "~60 % of full scale through the middle of the agar cylinder (r 12.9 mm) at "
                     "20 ms, or at 50 ms through its analyzer; thin samples need less",
                     min=0.0),
    "target_mm": Setting("list[float]", [0.0, 5.0], "beam target (lateral y, height z above "
                         "the plate), stage frame, until aim() is called; the beam comes from "
                         "the far side and travels towards the camera (+x)", "mm", length=2),
    "node_spacing_mm": Setting("float", 1.0, "node spacing of the tetrahedral mesh of the true "
                               "sample on which the light inside it is computed", "mm",
                               min=0.2),
    "flat_field_radiance": Setting("float", 0.12, "radiance of the flat-field diffuser shown "
                                   "by flat_field(True), relative units (0.12 ≈ half full "
                                   "well at 50 ms without an analyzer)", min=0.0),
}


# ---- the shared world -----------------------------------------------------------------------

class SimWorld:
    """State shared by the simulated devices of one rig."""

    def __init__(self) -> None:
        self.clock = SimClock()  # the time model (dotshell_sim.timing)
        self.camera: SimCamera | None = None
        self.projector: SimProjector | None = None
        self.stage: SimTurntable | None = None
        self.analyzer: SimAnalyzer | None = None
        self.laser: SimLaser | None = None
        self._key_memo: tuple[tuple, str] | None = None  # (devices and scene, renderer key)

    def require(self, who: str) -> tuple[SimProjector, SimTurntable]:
        missing = [(role, name) for role, name, dev in
                   (("projector", "sim-projector", self.projector),
                    ("stage", "sim-turntable", self.stage)) if dev is None]
        if missing:
            names = " and no ".join(name for _, name in missing)
            fix = " and ".join(f'[{role}] backend = "{name}"' for role, name in missing)
            raise DeviceError(
                f"{who}: the simulated camera has nothing to look at: this rig has no {names}. "
                f"Add {fix} to the profile (the sim devices of one rig share one world).")
        return self.projector, self.stage  # type: ignore[return-value]

    def calibration(self, who: str = "sim-camera") -> RigCalibration:
        """The true rig geometry (source ``"ground-truth"``)."""
        if self.camera is None:
            raise DeviceError(f"{who}: no sim-camera in this rig; add [camera] backend = "
                              "\"sim-camera\" to the profile.")
        projector, stage = self.require(who)
        R, T = projector.pose()
        Rc, Tc = self.camera.pose()  # bench frame -> this camera's frame
        return RigCalibration(camera=self.camera.lens, projector=projector.lens, R=R @ Rc.T,
                              T=T - R @ Rc.T @ Tc, axis_point=Rc @ stage.axis_point + Tc,
                              axis_direction=Rc @ stage.axis_direction, source="ground-truth")

    def state_digest(self, exposure_ms: float, light: bytes | None = None) -> bytes:
        """A digest of everything a frame depends on (pattern shown, stage and analyzer
        angles, laser and flat field, exposure): the camera seeds its noise with it, so a frame
        depends on the state it was taken in, not on how many frames came before — a resumed
        scan captures the same frames as an uninterrupted one. ``light``: the digest of what
        the panel showed during the exposure (:meth:`SimProjector.light_digest`); the newest
        pattern's when omitted."""
        import hashlib

        h = hashlib.blake2b(digest_size=16)
        if self.projector is not None:
            h.update(self.projector.pattern_digest if light is None else light)
        if self.stage is not None:
            h.update(repr((round(self.stage.position, 6), self.stage.target_key)).encode())
        if self.analyzer is not None and self.analyzer.connected:
            h.update(repr(round(self.analyzer.angle_deg, 6)).encode())
        if self.laser is not None:
            h.update(repr((self.laser.on, self.laser.flat, self.laser.target)).encode())
        h.update(repr(round(exposure_ms, 9)).encode())
        return h.digest()

    def renderer(self) -> Renderer:
        """The renderer for this world's geometry. Renderers are pure functions of the
        geometry, so worlds with identical settings (e.g. many test rigs from one profile)
        share one, with its cached camera rays and views."""
        projector, stage = self.require("sim-camera")
        s = self.camera.settings
        return cached(_RENDERERS, self._renderer_key(), lambda: Renderer(
            self.calibration(), stage.scene, supersample=s["supersample"], ambient=s["ambient"],
            projector_ref_mm=projector.ref_mm), _MAX_RENDERERS)

    def _renderer_key(self) -> str:
        """The geometry's key in :data:`_RENDERERS`, made again only when a device or the
        stage's scene changed (a frame asked for it: the calibration's JSON at every frame was
        ~1 % of a reduced scan)."""
        projector, stage = self.require("sim-camera")
        state = (self.camera, projector, stage, stage.scene, stage.target_key)
        memo = self._key_memo
        if memo is None or memo[0] != state:  # the devices and scene compare by identity
            memo = self._key_memo = (state, self._geometry_key(projector, stage))
        return memo[1]

    def _geometry_key(self, projector: SimProjector, stage: SimTurntable) -> str:
        s = self.camera.settings
        return json.dumps([self.calibration().to_dict(), stage.settings["scene"],
                           stage.settings["plate"], stage.settings["background"],
                           s["supersample"], s["ambient"], projector.ref_mm, stage.target_key],
                          sort_keys=True)

    def release_renderer(self) -> None:
        """Free the shared renderer's cached views, rays and laser views when they are large:
        a closed rig's views are rarely asked for again, and at full resolution they hold
        ~0.3 GB (a scan's merge, validation and previews run after the rig is closed). Small
        ones (below :data:`~dotshell_sim.render.SMALL_VIEWS_BYTES`) stay for the next rig of
        the same geometry."""
        renderer = self._made_renderer()
        if renderer is not None:
            renderer.release(keep_below_bytes=SMALL_VIEWS_BYTES)
            transillum.release_laser_views(renderer, keep_below_bytes=SMALL_VIEWS_BYTES)

    def release_laser_views(self) -> None:
        """Free the shared renderer's laser views when they are large: the laser was switched
        off, and a scan turns on to another angle, whose laser view is made anew. At full
        resolution the last angle's (~0.12 GB) stayed through the fringe views up to the next
        trans-illumination angle, beside a view's capture and reconstruction (issue 33)."""
        renderer = self._made_renderer()
        if renderer is not None:
            transillum.release_laser_views(renderer, keep_below_bytes=SMALL_VIEWS_BYTES)

    def _made_renderer(self) -> Renderer | None:
        """The renderer of this world's geometry if one was made, else None."""
        if self.camera is None:
            return None
        try:
            return _RENDERERS.get(self._renderer_key())
        except DeviceError:  # not a complete rig: no renderer was made
            return None


#: Renderers shared across worlds, by geometry (a full-resolution renderer with its cached
#: view and rays holds ~0.2 GB; a closed camera releases them).
_RENDERERS: OrderedDict[str, Renderer] = OrderedDict()
_MAX_RENDERERS = 2


def look_at_pose(s: dict, name: str, what: str) -> tuple[np.ndarray, np.ndarray]:
    """(R, T) with X_device = R @ X_bench + T for a device at ``position_mm`` looking at
    ``look_at_mm`` with ``up`` towards its image's row 0 (bench frame, mm)."""
    c = np.asarray(s["position_mm"], float)
    z = np.asarray(s["look_at_mm"], float) - c
    if np.linalg.norm(z) < 1e-6:
        raise DeviceError(f"{name}: look_at_mm equals position_mm; the {what} needs a point to "
                          "look at.")
    z /= np.linalg.norm(z)
    y = -np.asarray(s["up"], float)
    y = y - z * (y @ z)
    if np.linalg.norm(y) < 1e-6:
        raise DeviceError(f"{name}: 'up' is parallel to the viewing direction; give an up "
                          "direction across it (e.g. the turntable axis).")
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    R = np.vstack([x, y, z])
    return R, -R @ c


def world_of(context: RigContext | None) -> SimWorld:
    """The rig's simulator world (created on first use)."""
    if context is None:
        return SimWorld()
    world = context.shared.get(WORLD_KEY)
    if world is None:
        world = context.shared[WORLD_KEY] = SimWorld()
    return world


def _digest(image: np.ndarray) -> bytes:
    import hashlib

    return hashlib.blake2b(np.ascontiguousarray(image).tobytes(), digest_size=16).digest()


class _Device:
    name = "sim"

    def __init__(self, settings: dict, world: SimWorld):
        self.settings = settings
        self.world = world
        self.connected = False

    def connect(self) -> None:
        self.connected = True

    def close(self) -> None:
        self.connected = False

    def _check(self, action: str) -> None:
        if not self.connected:
            raise DeviceError(f"{self.name}: cannot {action} before connect(); connect the "
                              "rig first.")

    def status(self) -> dict[str, Any]:
        return {"connected": self.connected, "simulated": True}


# ---- devices --------------------------------------------------------------------------------

class SimCamera(_Device):
    """Renders the world; satisfies Camera, ExposureControl, FrameInfoSource, TriggeredCamera
    (its trigger input wired to the sim projector's trigger output) and GroundTruth.

    Time model (:mod:`dotshell_sim.timing`): ``capture()`` exposes over
    ``[now, now + exposure]`` and takes exposure + ``readout_ms``; a triggered frame exposes
    from its trigger edge. A frame's noise is seeded by the rig's state during its exposure
    (the light on the panel included), the same in both paths, so a triggered view and a
    captured view of the same light are the same frames."""

    name = "sim-camera"

    def __init__(self, settings: dict, world: SimWorld):
        super().__init__(settings, world)
        s = settings
        self.lens: Lens = lens_from_fov(s["width"], s["height"], s["focal_px"], s["dist"],
                                        s["cx"], s["cy"])
        self.pose()  # validate the geometry now
        full_scale = (1 << s["bit_depth"]) - 1
        self.sensor = SensorModel(s["bit_depth"], s["full_well_e"], s["read_noise_e"],
                                  s["gain_dn_per_e"] or full_scale / s["full_well_e"],
                                  s["dark_offset_dn"])
        self.exposure_ms = float(s["exposure_ms"])
        self.frames = 0
        self._info = FrameInfo(timestamp_s=float("nan"))
        self._armed: tuple[int, float] | None = None  # (frames wanted, armed at clock time)
        self._repeats: dict[bytes, int] = {}
        self._vignetting_map: tuple[float, np.ndarray] | None = None  # (loss, map)
        world.camera = self
        #: The rig's context (set by :func:`make_camera`): rendering runs in its
        #: ``computing()`` blocks, so the rig's call timeouts count only the modelled hardware's
        #: time, never the host's rendering time.
        self.rig_context = RigContext()

    @property
    def resolution(self) -> tuple[int, int]:
        return self.lens.size

    @property
    def bit_depth(self) -> int:
        return self.sensor.bit_depth

    def set_exposure(self, ms: float) -> None:
        if not (isinstance(ms, (int, float)) and math.isfinite(ms) and ms > 0):
            raise DeviceError(f"{self.name}: exposure must be a positive number of ms, got {ms!r}.")
        self.exposure_ms = float(ms)

    def ground_truth_calibration(self) -> RigCalibration:
        return self.world.calibration(self.name)

    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        """(R, T) with X_camera = R @ X_bench + T (identity at the default pose)."""
        return look_at_pose(self.settings, self.name, "camera")

    def close(self) -> None:
        super().close()
        self.world.release_renderer()

    def expected_electrons(self, start_s: float | None = None) -> np.ndarray:
        """Noise-free signal (H, W) float32 in electrons of an exposure starting at clock time
        ``start_s`` (now when omitted)."""
        self._check("capture")
        projector, stage = self.world.require(self.name)
        t0 = self.world.clock.now() if start_s is None else start_s
        radiance = projector.radiance_during(t0, t0 + self.exposure_ms / 1000.0)
        renderer = self.world.renderer()
        view = renderer.view(stage.position)
        light = renderer.render(view, radiance)
        if self.world.laser is not None:  # trans-illumination laser, flat-field diffuser
            light = self.world.laser.light(light, renderer, view)
        analyzer = self.world.analyzer
        if analyzer is not None and analyzer.connected:
            t_pol, t_dep = analyzer.transmission()
            irr = light.polarized * np.float32(t_pol) + light.depolarized * np.float32(t_dep)
        else:  # no analyzer in the light path
            irr = light.total
        irr *= np.float32(self.settings["sensitivity_e_per_ms"] * self.exposure_ms)
        if self.settings["vignetting"] > 0:  # extra lens fall-off (the flat field sees it too)
            irr *= self._vignetting()
        sigma = self.settings["defocus_sigma_px"]
        if sigma > 0:
            irr = cv2.GaussianBlur(irr, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        return irr

    def _vignetting(self) -> np.ndarray:
        """The extra lens vignetting map (H, W) float32, made once (~2 ms a frame at 320x256)."""
        loss = self.settings["vignetting"]
        if self._vignetting_map is None or self._vignetting_map[0] != loss:
            self._vignetting_map = (loss, transillum.lens_vignetting(self.lens, loss))
        return self._vignetting_map[1]

    def _frame(self, start_s: float, trigger: str) -> np.ndarray:
        """One frame exposed from clock time ``start_s``; its noise is seeded by the setting
        ``seed``, the world's state (the light on the panel during the exposure included) and
        how many frames were taken in that same state before (see
        :meth:`SimWorld.state_digest`)."""
        exposure_s = self.exposure_ms / 1000.0
        with self.world.clock.computing(), self.rig_context.computing():
            electrons = self.expected_electrons(start_s)
            light = self.world.projector.light_digest(start_s, start_s + exposure_s)
            state = self.world.state_digest(self.exposure_ms, light)
            repeat = self._repeats.get(state, 0)
            self._repeats[state] = repeat + 1
            rng = np.random.default_rng([self.settings["seed"], repeat,
                                         *np.frombuffer(state, np.uint32).tolist()])
            frame = sensor(electrons, self.sensor, rng)
        self._info = FrameInfo(timestamp_s=start_s, frame_id=self.frames,
                               exposure_ms=self.exposure_ms, extra={"trigger": trigger})
        self.frames += 1
        return frame

    def capture(self) -> np.ndarray:
        clock = self.world.clock
        t0 = clock.now()
        frame = self._frame(t0, "software")
        clock.advance_to(t0 + (self.exposure_ms + self.settings["readout_ms"]) / 1000.0)
        return frame

    def last_frame_info(self) -> FrameInfo:
        return self._info

    # ---- triggered frames (TriggeredCamera) ---------------------------------------------------

    def min_trigger_period_ms(self, exposure_ms: float) -> float:
        """Shortest time between trigger edges this camera keeps up with, in ms."""
        readout = self.settings["readout_ms"]
        return max(exposure_ms, readout) if self.settings["overlap_readout"] else (
            exposure_ms + readout)

    def arm(self, n_frames: int, exposure_ms: float) -> None:
        self._check("arm for triggered frames")
        if not (isinstance(n_frames, int) and n_frames > 0):
            raise DeviceError(f"{self.name}: arm() needs a positive number of frames, got "
                              f"{n_frames!r}.")
        self.set_exposure(exposure_ms)
        self._armed = (n_frames, self.world.clock.now())

    def read_armed(self, timeout_s: float) -> list[tuple[np.ndarray, FrameInfo]]:
        if self._armed is None:
            raise DeviceError(f"{self.name}: read_armed() before arm(); arm the camera first.")
        wanted, armed_at = self._armed
        clock = self.world.clock
        deadline = clock.now() + timeout_s
        projector = self.world.projector
        edges = [] if projector is None else [
            t for t in projector.timeline.triggers_s if armed_at <= t <= deadline]
        frames, busy_until, missed = [], -math.inf, 0
        exposure_s = self.exposure_ms / 1000.0
        for t in edges:
            if len(frames) == wanted:
                break
            if t < busy_until - 1e-9:
                missed += 1
                continue
            frames.append((self._frame(t, "projector"), self._info))
            busy_until = t + self.min_trigger_period_ms(self.exposure_ms) / 1000.0
        self._armed = None
        if len(frames) < wanted:
            clock.advance_to(deadline)
            why = (f"{missed} trigger edges came faster than the camera's "
                   f"{self.min_trigger_period_ms(self.exposure_ms):.2f} ms minimum period"
                   if missed else "no more trigger edges came: is the projector's trigger out "
                   "wired to the camera and its sequence started?")
            raise DeviceTimeout(f"{self.name}: {len(frames)} of {wanted} triggered frames "
                                f"arrived within {timeout_s:.3f} s; {why}")
        clock.advance_to(frames[-1][1].timestamp_s + exposure_s
                         + self.settings["readout_ms"] / 1000.0)
        return frames

    def disarm(self) -> None:
        self._armed = None

    def status(self) -> dict[str, Any]:
        out = {**super().status(), "exposure_ms": self.exposure_ms, "frames": self.frames,
               "resolution": list(self.resolution), "bit_depth": self.bit_depth}
        if self._armed is not None:
            out["armed_frames"] = self._armed[0]
        return out


class SimProjector(_Device):
    """The panel and optics of a projector: shows patterns on a display timeline (see
    :mod:`dotshell_sim.timing`) the camera integrates over its exposures. Satisfies Projector
    and SequencedProjector (a stored sequence run by the projector's own clock with a trigger
    edge at the start of each pattern, wired to the sim camera's trigger input)."""

    name = "sim-projector"

    def __init__(self, settings: dict, world: SimWorld):
        super().__init__(settings, world)
        s = settings
        self.lens: Lens = lens_from_fov(s["width"], s["height"], s["focal_px"], s["dist"],
                                        s["cx"], s["cy"])
        if s["pixel_aspect"] != 1.0:
            K = self.lens.K.copy()
            K[1, 1] *= s["pixel_aspect"]
            self.lens = Lens(K, self.lens.dist, self.lens.width, self.lens.height)
        self.ref_mm = float(np.linalg.norm(np.subtract(s["look_at_mm"], s["position_mm"])))
        self.pose()  # validate the geometry now
        self.timeline = DisplayTimeline()
        self._radiance_cache: OrderedDict[int, tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self._sequence: tuple[list[SequencePattern], float, float] | None = None
        self.last_shown: tuple[str, int] = ("", -1)
        self._running_until = -math.inf
        self._digests: dict[int, tuple[np.ndarray, bytes]] = {}
        world.projector = self

    @property
    def resolution(self) -> tuple[int, int]:
        return self.lens.size

    @property
    def clock(self) -> SimClock:
        return self.world.clock

    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        """(R, T) with X_projector = R @ X_bench + T, from position / look-at / up."""
        return look_at_pose(self.settings, self.name, "projector")

    def connect(self) -> None:
        super().connect()
        black = np.zeros((self.lens.height, self.lens.width), np.uint8)
        self.timeline.show(self.clock.now(), black)  # powered on showing black

    def close(self) -> None:
        super().close()
        self._sequence = None
        self._radiance_cache.clear()

    def check_pattern(self, pattern: np.ndarray) -> np.ndarray:
        """``pattern`` as the panel takes it: uint8 (or bool) of shape (height, width)."""
        p = np.asarray(pattern)
        w, h = self.resolution
        if p.shape != (h, w) or p.dtype not in (np.uint8, np.bool_):
            raise DeviceError(f"{self.name}: pattern must be a uint8 array of shape ({h}, {w}), "
                              f"got {p.dtype} {p.shape}.")
        return p

    def show(self, pattern: np.ndarray, name: str = "", index: int = -1) -> None:
        self._check("show a pattern")
        p = self.check_pattern(pattern).copy()
        s = self.settings
        at = display_time(self.clock.now(), s["display_latency_ms"], s["refresh_hz"])
        self.timeline.show(at, p, name, index)
        self.last_shown = (name, index)

    def radiance_of(self, image: np.ndarray | None) -> np.ndarray | None:
        """Relative radiance (h, w) float32 of a panel image after defocus; ``None`` = dark."""
        if image is None:
            return None
        key = id(image)
        hit = self._radiance_cache.get(key)
        if hit is not None and hit[0] is image:
            return hit[1]
        s = self.settings
        # in place, in float32 (the same operations in the same order as
        # brightness · (black + (1 - black) · img)): a full-size panel (912 x 1140 on a
        # LightCrafter, whatever the camera's scale) is 4 MiB an array, and each fresh one is
        # a new mapping whose pages fault in (dotshell.runtime.process.fix_mmap_threshold)
        img = image.astype(np.float32)
        img *= np.float32(1.0 if image.dtype == np.bool_ else 1 / 255.0)
        img *= 1 - s["black_level"]
        img += s["black_level"]
        img *= s["brightness"]
        if s["defocus_sigma_px"] > 0:
            img = cv2.GaussianBlur(img, (0, 0), s["defocus_sigma_px"],
                                   borderType=cv2.BORDER_CONSTANT)
        self._radiance_cache[key] = (image, img)
        while len(self._radiance_cache) > 4:
            self._radiance_cache.popitem(last=False)
        return img

    def _image_digest(self, image: np.ndarray | None) -> bytes:
        if image is None:
            return b"dark"
        hit = self._digests.get(id(image))
        if hit is None or hit[0] is not image:
            hit = self._digests[id(image)] = (image, _digest(image))
            while len(self._digests) > 8:
                self._digests.pop(next(iter(self._digests)))
        return hit[1]

    @property
    def pattern_digest(self) -> bytes:
        """Digest of the newest pattern on the timeline (b"" before any)."""
        image = self.timeline.segments[-1].image
        return b"" if image is None and len(self.timeline.segments) == 1 else (
            self._image_digest(image))

    def light_digest(self, t0_s: float, t1_s: float) -> bytes:
        """Digest of what the panel showed over ``[t0, t1)``: the pattern's digest when one
        pattern covered it, else of every pattern with its share."""
        parts = [(w, seg) for w, seg in self.timeline.weights(t0_s, t1_s) if w > 1e-9]
        if not self.connected:
            return b"off"
        if len(parts) == 1:
            return self._image_digest(parts[0][1].image)
        return _digest(np.frombuffer(b"".join(
            repr(round(w, 6)).encode() + self._image_digest(seg.image) for w, seg in parts),
            np.uint8))

    def radiance_during(self, t0_s: float, t1_s: float) -> np.ndarray | None:
        """Mean relative radiance (h, w) float32 over the clock window ``[t0, t1)`` (an
        exposure); ``None`` when the panel is dark (or off) throughout."""
        if not self.connected:
            return None
        parts = [(w, seg) for w, seg in self.timeline.weights(t0_s, t1_s) if w > 1e-9]
        lit = [(w, seg) for w, seg in parts if seg.image is not None]
        if not lit:
            return None
        if len(parts) == 1:  # one image for the whole exposure: exactly its radiance
            return self.radiance_of(lit[0][1].image)
        out = np.zeros((self.lens.height, self.lens.width), np.float32)
        for w, seg in lit:
            out += np.float32(w) * self.radiance_of(seg.image)
        return out

    # ---- hardware sequences (SequencedProjector) ---------------------------------------------

    def shortest_period_ms(self, exposure_ms: float, at_least_ms: float) -> float:
        return max(float(exposure_ms), float(at_least_ms))

    def load_sequence(self, patterns, exposure_ms: float, period_ms: float) -> None:
        self._check("load a pattern sequence")
        if not patterns:
            raise DeviceError(f"{self.name}: an empty pattern sequence cannot be loaded.")
        if not (0 < exposure_ms <= period_ms):
            raise DeviceError(f"{self.name}: pattern exposure {exposure_ms} ms must be positive "
                              f"and at most the period {period_ms} ms.")
        stored = [SequencePattern(self.check_pattern(p.image).copy(), p.name, p.index)
                  for p in patterns]
        self._sequence = (stored, float(exposure_ms), float(period_ms))

    def start_sequence(self) -> None:
        self._check("start a pattern sequence")
        if self._sequence is None:
            raise DeviceError(f"{self.name}: start_sequence() before load_sequence(); load the "
                              "patterns first.")
        stored, exposure_ms, period_ms = self._sequence
        start = self.clock.now()
        self.timeline.run_sequence(start, [(p.image, p.name, p.index) for p in stored],
                                   exposure_ms / 1000.0, period_ms / 1000.0)
        self._running_until = start + len(stored) * period_ms / 1000.0

    def stop_sequence(self) -> None:
        now = self.clock.now()
        if now < self._running_until:  # a finished sequence leaves the panel dark anyway
            self.timeline.stop(now)
        self._running_until = -math.inf

    def status(self) -> dict[str, Any]:
        out = {**super().status(), "resolution": list(self.resolution)}
        name, index = self.last_shown
        if name or index >= 0:
            out.update(pattern=name, pattern_index=index)
        if self._sequence is not None:
            out["sequence_patterns"] = len(self._sequence[0])
        return out


class SimTurntable(_Device):
    """Rotation stage carrying the scene; stores the angle."""

    name = "sim-turntable"

    def __init__(self, settings: dict, world: SimWorld):
        super().__init__(settings, world)
        s = settings
        self.axis_point = np.asarray(s["axis_point_mm"], float)
        d = np.asarray(s["axis_direction"], float)
        if np.linalg.norm(d) < 1e-9:
            raise DeviceError(f"{self.name}: axis_direction must not be zero.")
        self.axis_direction = d / np.linalg.norm(d)
        if np.linalg.norm(np.cross(self.axis_point, self.axis_direction)) < 1e-6:
            raise DeviceError(f"{self.name}: the rotation axis passes through the camera centre; "
                              "check axis_point_mm / axis_direction (camera frame, mm).")
        self.scene = build_scene(s["scene"], s["plate"], s["background"])
        self.target_key: str | None = None  # the calibration target on the stage, if any
        self._angle = 0.0
        self.follow: Any = None  # mixed rigs: () -> the real stage's angle (degrees)
        if world.stage is not None:
            raise DeviceError(f"{self.name}: this rig has both [stage] backend = "
                              "\"sim-turntable\" and [camera.settings.turntable]; keep one.")
        world.stage = self

    def place_target(self, board: dict | None, pose: dict | None) -> None:
        """Put the calibration board (see :mod:`dotshell_sim.target`) on the stage at ``pose``
        (sample frame); ``None`` takes it off. Satisfies ``dotshell.calibrate.TargetPlacement``."""
        from dotshell_sim.target import with_target

        s = self.settings
        self.scene = build_scene(s["scene"], s["plate"], s["background"])
        self.target_key = None
        if board is not None and pose is not None:  # the sample is taken off to calibrate
            self.scene = with_target(build_scene({**s["scene"], "kind": "none"}, s["plate"],
                                                 s["background"]), board, pose)
            self.target_key = json.dumps([board, pose], sort_keys=True)

    def move_to(self, degrees: float) -> None:
        self._check("move")
        if not (isinstance(degrees, (int, float)) and math.isfinite(degrees)):
            raise DeviceError(f"{self.name}: angle must be a finite number of degrees, got "
                              f"{degrees!r}.")
        spd = self.settings["steps_per_degree"]
        self._angle = round(degrees * spd) / spd if spd > 0 else float(degrees)

    def home(self) -> None:
        self._check("home")
        self._angle = 0.0

    @property
    def position(self) -> float:
        return float(self.follow()) if self.follow is not None else self._angle

    def status(self) -> dict[str, Any]:
        return {**super().status(), "angle_deg": self.position}


class SimAnalyzer(_Device):
    """Linear polarization analyzer in front of the camera (the projector carries the
    polarizer). Polarized light passes by Malus' law, cos²φ, down to 1/extinction_ratio;
    unpolarized light passes half (the mean of the two axes)."""

    name = "sim-analyzer"

    def __init__(self, settings: dict, world: SimWorld):
        super().__init__(settings, world)
        self._angle_deg = float(settings["initial_deg"])
        self.follow: Any = None  # mixed rigs: () -> the real analyzer's angle (degrees)
        if world.analyzer is not None:
            raise DeviceError(f"{self.name}: this rig has both [analyzer] backend = "
                              "\"sim-analyzer\" and [camera.settings.analyzer]; keep one.")
        world.analyzer = self

    @property
    def angle_deg(self) -> float:
        """The analyzer angle (degrees): its own, or the real mount's it follows."""
        return float(self.follow()) if self.follow is not None else self._angle_deg

    def set_angle(self, degrees: float) -> None:
        self._check("set the analyzer angle")
        if not (isinstance(degrees, (int, float)) and math.isfinite(degrees)):
            raise DeviceError(f"{self.name}: angle must be a finite number of degrees, got "
                              f"{degrees!r}.")
        self._angle_deg = float(degrees)

    def transmission(self) -> tuple[float, float]:
        """(transmission of the projector-polarized light, of unpolarized light)."""
        t = self.settings["transmittance"]
        leak = 1.0 / self.settings["extinction_ratio"]
        c2 = math.cos(math.radians(self.angle_deg)) ** 2
        return t * (c2 + leak * (1 - c2)), t * (1 + leak) / 2

    def status(self) -> dict[str, Any]:
        return {**super().status(), "angle_deg": self.angle_deg}


class SimLaser(_Device):
    """Trans-illumination laser and flat-field diffuser (:mod:`dotshell_sim.transillum`);
    satisfies LightSource, Targetable, FlatFieldReference and TransilluminationTruth.

    The beam is fixed in the stage frame, travelling along +x (towards the camera) at
    ``target`` = (y, z) mm; the light leaving the true sample is computed by the diffusion FEM
    and rendered by the camera. ``flat_field(True)`` puts a uniform diffuser in front of the
    camera instead of the scene."""

    name = "sim-laser"

    def __init__(self, settings: dict, world: SimWorld):
        super().__init__(settings, world)
        self.on = False
        self.flat = False
        self.target: tuple[float, float] = tuple(float(v) for v in settings["target_mm"])
        self._falloff: tuple[Any, np.ndarray] | None = None
        world.laser = self

    def set(self, on: bool) -> None:
        self._check("switch the laser")
        self.on = bool(on)  # what it shines through is checked by aim() and at capture
        if not self.on:
            self.world.release_laser_views()

    def aim(self, target_mm: tuple[float, float]) -> None:
        self._check("aim the laser")
        t = list(target_mm) if isinstance(target_mm, (list, tuple, np.ndarray)) else []
        if len(t) != 2 or not all(isinstance(v, (int, float, np.number)) and math.isfinite(v)
                                  for v in t):
            raise DeviceError(f"{self.name}: target must be (lateral y, height z) in mm, got "
                              f"{target_mm!r}.")
        shape, material = self._sample()
        transillum.sample_optics(self._stage().settings["scene"], material, self.name)
        transillum.require_entry(shape, self._stage().position, t, self.name)
        self.target = (float(t[0]), float(t[1]))

    def flat_field(self, on: bool) -> None:
        self._check("move the flat-field diffuser")
        self.flat = bool(on)

    def close(self) -> None:
        self.on = False
        self.flat = False
        super().close()

    def status(self) -> dict[str, Any]:
        return {**super().status(), "on": self.on, "target_mm": list(self.target),
                "flat_field": self.flat}

    # ---- for the camera and the truth --------------------------------------------------------

    def _stage(self) -> SimTurntable:
        if self.world.stage is None:
            raise DeviceError(f"{self.name}: no sim-turntable in this rig, so there is no sample "
                              "to trans-illuminate; add [stage] backend = \"sim-turntable\".")
        return self.world.stage

    def _sample(self):
        """(true sample shape, its material)."""
        stage = self._stage()
        if stage.settings["scene"]["kind"] == "none" or stage.target_key is not None:
            raise DeviceError(f"{self.name}: there is no sample on the stage (scene kind "
                              f"{stage.settings['scene']['kind']!r} or a calibration target); "
                              "put a sample on the stage to trans-illuminate it.")
        shape = stage.scene.sample[0]
        return shape, stage.scene.materials[shape.material]

    def _model(self) -> transillum.FluenceModel:
        shape, material = self._sample()
        optics = transillum.sample_optics(self._stage().settings["scene"], material, self.name)
        return transillum.fluence_model(shape, optics, self.settings["node_spacing_mm"])

    def light(self, base: Light, renderer: Renderer, view) -> Light:
        """The camera's light with the diffuser (replaces the scene) or the laser (adds)."""
        if self.connected and self.flat:
            lens = renderer.calib.camera
            if self._falloff is None or self._falloff[0] is not lens:
                self._falloff = (lens, transillum.natural_falloff(lens))
            flat = self._falloff[1] * np.float32(self.settings["flat_field_radiance"])
            return Light(np.zeros_like(flat), flat)
        if not (self.connected and self.on) or self.settings["power"] == 0:
            return base
        shape, _ = self._sample()
        img = transillum.laser_irradiance(renderer, view, shape, self._model(), self.target)
        return Light(base.polarized, base.depolarized + img * np.float32(self.settings["power"]))

    def true_normal_radiance(self, angle_deg: float, target_mm: tuple[float, float] | None,
                             points_mm: np.ndarray) -> np.ndarray:
        """See :class:`dotshell.devices.TransilluminationTruth`: P · φ · L(0°)/φ in camera DN
        per ms at the principal point (× the analyzer's transmission of unpolarized light
        when the rig has one: it sits in the light path while scanning); NaN farther than
        1 mm from the true surface. ``target_mm`` None = the current target (an un-aimed
        source). Works on devices that are built but not connected."""
        model, radiance = self._true_radiance(angle_deg, target_mm)
        value, dist = model.surface_fluence(radiance, np.asarray(points_mm, float).reshape(-1, 3))
        return np.where(dist <= transillum.MAX_SNAP_MM, value, np.nan)

    def true_surface_radiance(self, angle_deg: float,
                              target_mm: tuple[float, float] | None) -> SurfaceRadiance:
        """See :class:`dotshell.devices.TransilluminationTruth`: the field
        :meth:`true_normal_radiance` reads, on the boundary of the true sample's FEM mesh."""
        model, radiance = self._true_radiance(angle_deg, target_mm)
        faces = np.asarray(model.mesh.boundary_faces, np.int64)
        used, triangles = np.unique(faces, return_inverse=True)
        return SurfaceRadiance(model.mesh.nodes[used], triangles.reshape(faces.shape),
                               radiance[used], transillum.MAX_SNAP_MM)

    def _true_radiance(self, angle_deg: float, target_mm: tuple[float, float] | None
                       ) -> tuple[transillum.FluenceModel, np.ndarray]:
        """The true sample's FEM and P · φ · L(0°)/φ per node of it, in DN per ms."""
        if target_mm is None:
            target_mm = self.target
        cam = self.world.camera
        if cam is None:
            raise DeviceError(f"{self.name}: the truth is in camera units; add [camera] "
                              "backend = \"sim-camera\" to the rig.")
        shape, _ = self._sample()
        model = self._model()
        entry, direction = transillum.require_entry(shape, angle_deg, target_mm, self.name)
        phi = model.fluence(model.source_inside(entry, direction))
        analyzer = self.world.analyzer
        through = analyzer.transmission()[1] if analyzer is not None else 1.0
        scale = (self.settings["power"] * float(exit_radiance_per_fluence(1.0, model.optics.n))
                 * cam.settings["sensitivity_e_per_ms"] * cam.sensor.gain_dn_per_e * through)
        return model, phi * scale


# ---- factories ------------------------------------------------------------------------------

def _factory(cls, schema, backend: str):
    def factory(settings: dict | None = None, context: RigContext | None = None):
        # settings arrive validated; validating again is idempotent and lets tests pass partial
        # dicts
        given = {k: v for k, v in (settings or {}).items() if v is not None}
        full = validate_settings(schema, given, backend)
        return cls(full, world_of(context))

    factory.__name__ = f"make_{cls.__name__}"
    return factory


_make_camera = _factory(SimCamera, CAMERA_SCHEMA, "sim-camera")


def make_camera(settings: dict | None = None, context: RigContext | None = None) -> SimCamera:
    """The sim camera; with a ``turntable`` setting (mixed rigs) also the simulated sample on
    whatever stage the rig has, turning to that stage's reported angle."""
    camera = _make_camera(settings, context)
    if context is not None:
        camera.rig_context = context
    if camera.settings["turntable"] is not None:
        table = validate_settings(TURNTABLE_SCHEMA, camera.settings["turntable"], "sim-camera",
                                  "camera.settings.turntable")
        SimTurntable(table, camera.world).follow = lambda: _rig_angle(context, "stage")
    if camera.settings["analyzer"] is not None:
        optics = validate_settings(ANALYZER_SCHEMA, camera.settings["analyzer"], "sim-camera",
                                   "camera.settings.analyzer")
        follower = SimAnalyzer(optics, camera.world)
        follower.follow = lambda: _rig_angle(context, "analyzer")
        follower.connected = True  # in the light path for as long as the camera is
    return camera


def _rig_angle(context: RigContext | None, role: str) -> float:
    """The angle (degrees) the rig's ``role`` device reports, which the sim camera's
    ``[camera.settings.turntable]`` (stage) or ``[camera.settings.analyzer]`` follows."""
    device = context.device(role) if context is not None else None
    if device is None:
        key = "turntable" if role == "stage" else role
        raise DeviceError(f"sim-camera: [camera.settings.{key}] follows the rig's {role}, but "
                          f"this rig has none; add a [{role}] section.")
    return float(device.position)
make_projector = _factory(SimProjector, PROJECTOR_SCHEMA, "sim-projector")
make_turntable = _factory(SimTurntable, TURNTABLE_SCHEMA, "sim-turntable")
make_analyzer = _factory(SimAnalyzer, ANALYZER_SCHEMA, "sim-analyzer")
make_laser = _factory(SimLaser, LASER_SCHEMA, "sim-laser")
