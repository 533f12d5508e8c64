"""Checks of a connected rig before it scans: refused camera controls, calibration against the
devices' resolutions, and the display latency that ``[scan] settle_ms`` must cover.

``dotshell check PROFILE --connect`` runs the first two, ``--latency`` the third; the runner
reports refused controls as warnings in the run's events.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from dotshell import devices
from dotshell.errors import CalibrationError, DeviceError
from dotshell.geometry.calibration import RigCalibration


def refused_controls(rig: Any) -> list[str]:
    """One line per control a device refused (``status()["refused_controls"]``), naming the
    role, the control and the device's reason."""
    out = []
    for role, status in rig.status().items():
        for name, why in (status.get("refused_controls") or {}).items():
            out.append(f"{role} refused {name}: {why}")
    return out


def resolution_mismatches(rig: Any, calib: RigCalibration) -> list[str]:
    """What differs between the calibration and the connected devices' resolutions."""
    out = []
    for role, lens in (("camera", calib.camera), ("projector", calib.projector)):
        size = tuple(int(v) for v in rig.devices[role].resolution)
        if size != tuple(lens.size):
            out.append(f"the {role} gives {size[0]}x{size[1]} px but the calibration's {role} "
                       f"is {lens.width}x{lens.height} px")
    return out


def check_resolutions(rig: Any, calib: RigCalibration, source: str) -> None:
    """CalibrationError naming every mismatch (before a scan, not after its first view)."""
    wrong = resolution_mismatches(rig, calib)
    if wrong:
        raise CalibrationError(f"{source}: {'; '.join(wrong)}. Calibrate this rig at these "
                               "resolutions (dotshell calibrate) or set the devices to the "
                               "calibrated ones.")


# ---- display latency ---------------------------------------------------------------------------

#: A frame counts as "white" once it reached this share of the black → white step.
WHITE_SHARE = 0.95
#: settle_ms = measured delay × (1 + margin), rounded up to 5 ms.
MARGIN = 0.25


@dataclass
class LatencyResult:
    """Display latency as the show/settle/capture path sees it (milliseconds).

    Attributes:
        settle_ms: what to put in ``[scan] settle_ms``.
        shortest_ms: the shortest wait after ``show()`` with which every trial's capture saw
            the full new pattern.
        trials: (wait ms, share of the black → white step seen) of every trial.
    """

    settle_ms: float
    shortest_ms: float
    contrast_dn: float
    trials: list[tuple[float, float]] = field(default_factory=list)


def _bright_mask(black: np.ndarray, white: np.ndarray) -> tuple[np.ndarray, float]:
    """Pixels the projector lights (at least half the 99th-percentile step) and their mean
    black → white step (DN)."""
    diff = white.astype(np.float64) - black.astype(np.float64)
    mask = diff > 0.5 * float(np.percentile(diff, 99))
    return mask, float(diff[mask].mean()) if mask.any() else 0.0


def measure_latency(rig: Any, exposure_ms: float, max_ms: float = 1000.0,
                    resolution_ms: float = 2.0, repeats: int = 3) -> LatencyResult:
    """Flip the projector between black and white and find the shortest wait after
    ``show(white)`` after which a capture sees the whole white (≥ 95 % of the step on the
    pixels the projector lights), each wait tried ``repeats`` times (the display's refresh
    phase varies). Search: doubling from ``resolution_ms`` up to ``max_ms``, then bisection.
    Only the waits are timed (by sleeping), never the captures, so the result is in the
    clock the runner's ``settle_ms`` sleeps in."""
    cam, proj = rig.camera, rig.projector
    if devices.implements(cam, devices.ExposureControl):
        cam.set_exposure(exposure_ms)
    w, h = proj.resolution
    black = np.zeros((h, w), np.uint8)
    white = np.full((h, w), 255, np.uint8)

    def settled(image: np.ndarray, wait_s: float) -> np.ndarray:
        proj.show(image, name="latency-check", index=-1)
        time.sleep(wait_s)
        return cam.capture()

    ref_black = settled(black, max_ms / 1000.0)
    ref_white = settled(white, max_ms / 1000.0)
    mask, step = _bright_mask(ref_black, ref_white)
    noise = float(np.std(ref_black.astype(np.float64)[mask])) if mask.any() else 0.0
    if not mask.any() or step < max(10.0, 5 * noise):
        raise DeviceError(f"latency check: the camera does not see the projector flip black → "
                          f"white (step {step:.1f} DN, noise {noise:.1f} DN); point the "
                          "projector at the camera's field (a white target), open the lens or "
                          "lengthen the exposure.")
    base = float(ref_black[mask].mean())
    trials: list[tuple[float, float]] = []

    def share(frame: np.ndarray) -> float:
        return (float(frame[mask].mean()) - base) / step

    def poll(until: Callable[[float], bool]) -> None:
        deadline = time.monotonic() + 5 * max_ms / 1000.0
        while not until(share(cam.capture())):
            if time.monotonic() > deadline:
                raise DeviceError("latency check: the camera image did not settle within "
                                  f"{5 * max_ms:.0f} ms; is the light in the scene changing?")

    def to_black() -> None:
        """A display with nothing in flight, showing black: wait for the last white to arrive
        (a trial that saw black left it on its way), then show black and wait to see it."""
        poll(lambda seen: seen >= WHITE_SHARE)
        proj.show(black, name="latency-check", index=-1)
        poll(lambda seen: seen <= 1 - WHITE_SHARE)

    def passes(wait_ms: float) -> bool:
        ok = True
        for _ in range(repeats):
            to_black()
            seen = share(settled(white, wait_ms / 1000.0))
            trials.append((wait_ms, seen))
            ok &= seen >= WHITE_SHARE
        return ok

    wait = resolution_ms
    while wait < max_ms and not passes(wait):
        wait *= 2
    if wait >= max_ms and not passes(max_ms):
        raise DeviceError(f"latency check: the camera still sees less than {WHITE_SHARE:.0%} of "
                          f"the white {max_ms:.0f} ms after show(); the display is slower than "
                          "that or the light changes (auto exposure on?).")
    hi_ms, lo_ms = min(wait, max_ms), (wait / 2 if wait > resolution_ms else 0.0)
    while hi_ms - lo_ms > resolution_ms:
        mid = (hi_ms + lo_ms) / 2
        if passes(mid):
            hi_ms = mid
        else:
            lo_ms = mid
    settle = 5.0 * math.ceil(hi_ms * (1 + MARGIN) / 5.0)
    return LatencyResult(settle_ms=settle, shortest_ms=hi_ms, contrast_dn=step, trials=trials)
