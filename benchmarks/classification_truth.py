"""Decoded share and wrong codes of each gray-code classification against the simulator's
ground truth (issue 27): ``contrast``, ``robust`` (the gray code's default), ``adaptive`` and
adaptive without its continuity test on
the metal cylinder (clean; and under room light as strong as the projector's with the camera
defocused to σ = 1.5 px), the agar cylinder without analyzer under strong room light (ambient
light + subsurface blur; and with the camera defocused too), the agar cylinder with PDI
(|I∥ − I⊥| frames), the mouse phantom (depth edges; its scan's 12 views summed) and the gummy
bear with PDI (4 views). Per scene and
classification: pixels decoded on the lit surface (share of the lit pixels), wrong codes there
(more than 1.5 projector px from the true column or row), pixels decoded off it, and the
neighbour-reversal estimate of wrong codes
(:func:`~dotshell.pipeline.decode_quality.view_quality`), and the decode time:
the classifications decoded in turn, in a rotating order, ``--repeats`` times after a warm-up
(min / median ms of wall time, and the median's ratio to robust's measured in the same rounds;
then the median CPU time of the process, every decoding thread counted, and its ratio: on a
busy shared host the steadier figure).

    PYTHONPATH=.:plugins:tests python benchmarks/classification_truth.py [--factor 0.25]
        [--repeats 3] [--scenes metal]      # --factor 1: full-resolution views
"""

from __future__ import annotations

import argparse
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

#: name → the gray code's settings besides ``axes``; "adaptive, no continuity" is adaptive
#: without its neighbour-continuity test (``adaptive_code_steps`` 0), for comparison
CLASSIFICATIONS = {"contrast": {"classification": "contrast"},
                   "robust": {"classification": "robust"},
                   "adaptive": {"classification": "adaptive"},
                   "adaptive, no continuity": {"classification": "adaptive",
                                               "adaptive_code_steps": 0}}
#: (name, profile, camera settings changed, PDI, stage angles of the views scored (degrees))
SCENES = (("clean metal", "sim-metal-cylinder", {}, False, (0.0,)),
          ("metal, room light 1, blur", "sim-metal-cylinder",
           {"ambient": 1.0, "defocus_sigma_px": 1.5}, False, (0.0,)),
          ("agar, room light 0.5", "sim-agar-cylinder-nopdi", {"ambient": 0.5}, False, (0.0,)),
          ("agar, room light 1, blur", "sim-agar-cylinder-nopdi",
           {"ambient": 1.0, "defocus_sigma_px": 1.5}, False, (0.0,)),
          ("agar PDI", "sim-agar-cylinder", {}, True, (0.0,)),
          # depth edges, ears and paws seen edge-on: the scan's 12 views
          ("mouse phantom, 12 views", "sim-mouse-phantom", {}, False,
           tuple(30.0 * k for k in range(12))),
          ("gummy bear PDI, 4 views", "sim-gummy-bear", {}, True, (0.0, 90.0, 180.0, 270.0)))


def scene_frames(profile: str, camera: dict, pdi: bool, factor: float, angle_deg: float = 0.0):
    """The gray-code frames of the scene's view at stage angle ``angle_deg`` (PDI: |I∥ − I⊥|
    per pattern), the projector size and the true (column, row, lit) per camera pixel."""
    from dotshell_codings.graycode import make_graycode
    from dotshell_sim.bench import scale_profile
    from sim_sequences import connected_rig, true_projector_coordinates

    raw = scale_profile(tomllib.loads((ROOT / "profiles" / f"{profile}.toml").read_text()),
                        factor)
    raw["camera"]["settings"].update(camera)
    rig = connected_rig(raw)
    rig["stage"].move_to(angle_deg)
    size = rig["projector"].resolution
    patterns = make_graycode({"axes": "both"}).patterns(size)
    angles = raw["scan"]["pdi_angles_deg"] if pdi else [None]
    shots = []
    for angle in angles:
        if angle is not None:
            rig["analyzer"].set_angle(float(angle))
        shots.append([])
        for pat in patterns:
            rig["projector"].show(pat.image)
            shots[-1].append(rig["camera"].capture())
    if pdi:
        frames = [np.abs(a.astype(np.int32) - b.astype(np.int32)).astype(a.dtype)
                  for a, b in zip(*shots)]
    else:
        frames = shots[0]
    return frames, size, true_projector_coordinates(rig, angle_deg)


def score(corr, u, v, lit) -> dict:
    """Decoded pixels on the lit surface, the wrong ones among them, decoded pixels off it."""
    from dotshell.pipeline.decode_quality import view_quality

    on = corr.valid & lit
    err = np.maximum(np.abs(corr.column - np.nan_to_num(u, nan=-1e6)),
                     np.abs(corr.row - np.nan_to_num(v, nan=-1e6)))
    return {"lit": int(lit.sum()), "decoded": int(on.sum()),
            "wrong": int(np.count_nonzero(on & (err > 1.5))),
            "off": int(np.count_nonzero(corr.valid & ~lit)),
            "reversals": view_quality(corr)["reversals"]}


def timed_decodes(frames, size, repeats: int) -> tuple[dict, dict, dict]:
    """Each classification's correspondence, decode wall times and CPU times (s), decoded in
    turn in a rotating order ``repeats`` times after a round that compiles and warms up."""
    from dotshell_codings.graycode import make_graycode

    codings = {c: make_graycode({"axes": "both", **settings})
               for c, settings in CLASSIFICATIONS.items()}
    names = list(CLASSIFICATIONS)
    times: dict[str, list[float]] = {c: [] for c in names}
    cpu: dict[str, list[float]] = {c: [] for c in names}
    out = {}
    for r in range(repeats + 1):
        k = r % len(names)
        for c in names[k:] + names[:k]:
            t0, c0 = time.perf_counter(), time.process_time()
            out[c] = codings[c].decode(frames, size)
            if r:
                times[c].append(time.perf_counter() - t0)
                cpu[c].append(time.process_time() - c0)
    return out, times, cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--factor", type=float, default=0.25, help="resolution factor (1 = full)")
    ap.add_argument("--repeats", type=int, default=3, help="timed rounds per scene")
    ap.add_argument("--scenes", default="", help="only the scenes whose name holds this")
    args = ap.parse_args()
    print(f"== gray-code classifications against ground truth, {args.factor:g}x "
          f"(ms: min / median of {args.repeats}) ==")
    print(f"  {'scene':26s} {'classification':24s} {'decoded on lit':>19s} {'wrong':>6s} "
          f"{'off lit':>8s} {'reversals':>9s} {'ms min / median':>17s} {'x robust':>8s} "
          f"{'CPU ms':>7s} {'x robust':>8s}")
    for name, profile, camera, pdi, angles in SCENES:
        if args.scenes not in name:
            continue
        scores: dict[str, dict] = {}
        times: dict[str, list[float]] = {c: [] for c in CLASSIFICATIONS}
        cpu: dict[str, list[float]] = {c: [] for c in CLASSIFICATIONS}
        for angle in angles:  # the views' figures summed, their times pooled
            frames, size, (u, v, lit) = scene_frames(profile, camera, pdi, args.factor, angle)
            out, t_view, cpu_view = timed_decodes(frames, size, args.repeats)
            for c in CLASSIFICATIONS:
                s = score(out[c], u, v, lit)
                scores[c] = {k: scores.get(c, {}).get(k, 0) + s[k] for k in s}
                times[c] += t_view[c]
                cpu[c] += cpu_view[c]
        base = float(np.median(times["robust"]))
        cpu_base = float(np.median(cpu["robust"]))
        for c in CLASSIFICATIONS:
            s = scores[c]
            t = np.array(times[c]) * 1e3
            print(f"  {name:26s} {c:24s} {s['decoded']:9d} ({100 * s['decoded'] / s['lit']:5.1f} %)"
                  f" {s['wrong']:6d} {s['off']:8d} {s['reversals']:9d} "
                  f"{t.min():7.1f} / {np.median(t):7.1f} {np.median(t) / 1e3 / base:8.2f} "
                  f"{np.median(cpu[c]) * 1e3:7.1f} {np.median(cpu[c]) / cpu_base:8.2f}")


if __name__ == "__main__":
    main()
