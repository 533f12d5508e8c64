"""Two cameras sharing one projector, everything calibrated through the documented commands
(issue 27).

Default: camera 1's camera–projector calibration from five gray-code board poses
(``dotshell calibrate --captures``), the camera pair from twelve board photos per camera
(``dotshell calibrate --camera-pair``), then ``dotshell reconstruct --captures --captures2
--camera-pair --calibration`` (``tests/test_code_stereo.py::calibrated_fusion``). Prints, for
camera–projector, camera–camera and fused points of the same pixels, the lateral points, the
fitted radius of the metal cylinder (true 7.7 mm) and the mean relative radius error about the
cloud's own fitted axis.

``--sim-profile``: the same from the shipped two-camera sim profile, its captures made by
``python -m dotshell_sim.two_camera sim-metal-cylinder-two-camera`` and the projector first
left uncalibrated (``tests/test_two_camera_sim.py::two_camera_commands``).

    PYTHONPATH=.:plugins:tests python benchmarks/camera_pair_fusion.py [--factor 0.25] [--sim-profile]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))


def sim_profile(factor: float) -> None:
    """The two-camera sim profile through the commands; prints its figures."""
    from test_two_camera_sim import print_figures, two_camera_commands

    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as d:
        figures = two_camera_commands(Path(d), factor)
    print_figures(figures, factor)
    print(f"  wall time {time.perf_counter() - t0:.0f} s (captures rendered, calibrated, "
          "reconstructed)")


def main() -> None:
    from test_code_stereo import calibrated_fusion

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--factor", type=float, default=0.25, help="resolution factor (1 = full)")
    ap.add_argument("--sim-profile", action="store_true",
                    help="the shipped two-camera sim profile, projector uncalibrated and fused")
    args = ap.parse_args()
    if args.sim_profile:
        return sim_profile(args.factor)
    with tempfile.TemporaryDirectory() as d:
        errs = calibrated_fusion(Path(d), args.factor)
    print(f"== two cameras + calibrated projector, metal cylinder, {args.factor:g}x, "
          "calibrated through the commands ==")
    for name, (n, radius, err) in errs.items():
        label = "fused" if name == "cloud" else name
        print(f"  {label:17s} {n:8d} points   radius {radius:.4f} mm   mean relative radius "
              f"error {err:.4f} % (own axis)")


if __name__ == "__main__":
    main()
