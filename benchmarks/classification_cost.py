"""What each gray-code classification costs on one view of the simulated bench, interleaved in
one run: ``robust``, ``adaptive`` (the gray code's default: robust's pass with a second chance
for the pixels robust leaves uncertain, after the camera noise model is counted), adaptive
without its neighbour-continuity test (``adaptive_code_steps = 0``: what that test costs) and
``contrast``; min / median ms per view and the ratios to robust, with the decoded pixels of
each.

    PYTHONPATH=.:plugins python benchmarks/classification_cost.py [--quick] [--repeats N]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_profile import load_bench_profile  # noqa: E402
from frame_io import min_median  # noqa: E402

#: name → the gray code's settings besides ``axes``
CLASSIFICATIONS = {"robust": {"classification": "robust"},
                   "adaptive": {"classification": "adaptive"},
                   "adaptive, no continuity": {"classification": "adaptive",
                                               "adaptive_code_steps": 0},
                   "contrast": {"classification": "contrast"}}


def bench_frames(quick: bool):
    """The bench's first view, every gray-code frame, and the projector size."""
    from dotshell.plugins import get_plugin_manager
    from dotshell.rig.assembly import Rig
    from dotshell_codings.graycode import make_graycode

    pm = get_plugin_manager()
    profile = load_bench_profile(pm, quick=quick)
    coding = make_graycode({"axes": "both"})
    with Rig(profile, pm) as rig:
        rig.camera.set_exposure(profile.data["scan"]["exposure_ms"])
        size = rig.projector.resolution
        frames = []
        for pattern in coding.patterns(size):
            rig.projector.show(pattern.image)
            frames.append(rig.camera.capture())
    return frames, size


def main() -> None:
    from dotshell_codings.graycode import make_graycode

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="reduced resolution")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    frames, size = bench_frames(args.quick)
    codings = {c: make_graycode({"axes": "both", **settings})
               for c, settings in CLASSIFICATIONS.items()}
    names = list(CLASSIFICATIONS)
    times = {c: [] for c in names}
    decoded = {}
    for r in range(args.repeats + 1):  # the first round compiles and warms up
        order = names[r % len(names):] + names[:r % len(names)]
        for c in order:
            t0 = time.perf_counter()
            corr = codings[c].decode(frames, size)
            if r:
                times[c].append(time.perf_counter() - t0)
            decoded[c] = int(corr.valid.sum())
    h, w = frames[0].shape
    print(f"== gray-code classifications on one {w}x{h} view ({len(frames)} frames; "
          f"min / median of {args.repeats}, ms) ==")
    base = min_median(times["robust"])
    for c in CLASSIFICATIONS:
        m = min_median(times[c])
        print(f"  {c:23s} {m['min'] * 1e3:8.1f} / {m['median'] * 1e3:8.1f}   "
              f"{m['median'] / base['median']:5.2f}x robust   {decoded[c]} px decoded")


if __name__ == "__main__":
    main()
