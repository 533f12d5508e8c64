"""The shipped two-camera sim profile through the documented commands (issue 27):
``python -m dotshell_sim.two_camera sim-metal-cylinder-two-camera`` makes the captures, then
``dotshell calibrate --camera-pair``, ``dotshell reconstruct --captures --captures2
--camera-pair`` (projector uncalibrated) and, with ``dotshell calibrate --captures``' projector
calibration, the fused reconstruction (``tests/test_two_camera_sim.py::two_camera_commands``).
Prints each cloud's lateral points, the fitted radius of the metal cylinder (true 7.7 mm) and
the mean relative radius error about the cloud's own fitted axis.

    PYTHONPATH=.:plugins:tests python benchmarks/two_camera_sim.py [--scale 1]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))


def main() -> None:
    from test_two_camera_sim import print_figures, two_camera_commands

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scale", type=float, default=1.0, help="resolution factor (1 = full)")
    args = ap.parse_args()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as d:
        figures = two_camera_commands(Path(d), args.scale)
    print_figures(figures, args.scale)
    print(f"  wall time {time.perf_counter() - t0:.0f} s (captures rendered, calibrated, "
          "reconstructed)")


if __name__ == "__main__":
    main()
