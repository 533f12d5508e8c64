"""Decoding one view four ways, timings interleaved in one run: dotshell's decoder, the decoder
before issue 16 part 2 (:mod:`graycode_before`, frozen), OpenCV contrib's ``getProjPixel`` on the
lit pixels in raster order (its own venv, a server process so its runs alternate with ours), and
the plain numpy integer decoder (:mod:`numpy_gray`).

Each repeat runs all of them (and dotshell's decoder with ``subpixel = false``, so that the
refinement's share shows), in a rotating order; min and median per side. Agreement: dotshell's
decoder against the one before, bit for bit (integer codes, masks, statistics, and the sub-pixel
coordinates); the numpy decoder and OpenCV against dotshell's integer codes (the same decoder
with ``subpixel = false``, so the compared values are integers on both sides).
"""

from __future__ import annotations

import inspect
import json
import subprocess
import time
from pathlib import Path
from collections.abc import Callable
from typing import Any

import numpy as np

import graycode_before
import numpy_gray
from dotshell.coding import Correspondence
from dotshell_codings.graycode import code_offset
from dotshell_codings.robust import full_scale
from frame_io import min_median

BENCH_DIR = Path(__file__).resolve().parent


def opencv_order(names: list[str]) -> list[int]:
    """Indices of our frames in OpenCV's order: each column bit's pattern and inverse (MSB
    first), the same for rows, then white and black. Ours: white, black, then the pairs; both
    codes light the stripe where the Gray bit is 1 in the non-inverse pattern."""
    pairs = [i for i, n in enumerate(names) if n.startswith("col_")] + \
            [i for i, n in enumerate(names) if n.startswith("row_")]
    return pairs + [names.index("white"), names.index("black")]


class OpenCVPeer:
    """``peer_opencv.py`` running in the contrib venv, timed one decode at a time."""

    def __init__(self, python: Path, frames: np.ndarray, names: list[str],
                 projector_size: tuple[int, int], bit_depth: int, work: Path) -> None:
        np.save(work / "peer_frames.npy", frames[opencv_order(names)])
        job = {"frames": str(work / "peer_frames.npy"), "projector": list(projector_size),
               "shift": max(0, bit_depth - 8), "white_threshold": 5, "black_threshold": 40}
        (work / "peer_job.json").write_text(json.dumps(job))
        self.out = work / "peer_out.npz"
        self.proc = subprocess.Popen([str(python), str(BENCH_DIR / "peer_opencv.py"),
                                      str(work / "peer_job.json"), str(self.out)],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self.info = self._answer()

    def _answer(self) -> dict[str, Any]:
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError("the OpenCV peer exited early (see its error above)")
        return json.loads(line)

    def time_once(self) -> float:
        """Seconds for getProjPixel over every lit pixel, measured inside the peer."""
        self.proc.stdin.write("time\n")
        self.proc.stdin.flush()
        return float(self._answer()["seconds"])

    def finish(self) -> dict[str, np.ndarray]:
        self.proc.stdin.write("done\n")
        self.proc.stdin.flush()
        if self.proc.wait(timeout=120) != 0:
            raise RuntimeError("the OpenCV peer failed")
        with np.load(self.out) as z:
            return {k: z[k] for k in z.files}


def _timed(fn) -> tuple[float, Any]:
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def frozen_settings(settings: dict[str, Any]) -> dict[str, Any]:
    """The coding's settings as the frozen decoder takes them: its own keys only, and
    ``classification = "robust"`` where the profile asks for one it predates (``adaptive``)."""
    known = inspect.signature(graycode_before.GrayCode.__init__).parameters
    out = {k: v for k, v in settings.items() if k in known}
    if out.get("classification", "robust") not in ("contrast", "robust"):
        out["classification"] = "robust"
    return out


def compare(view, integer_coding, peer: OpenCVPeer, repeats: int,
            settings: dict[str, Any], make_coding: Callable[..., Any]) -> dict[str, Any]:
    """Interleaved timings of the decoders on ``view`` and their agreement; ``settings``: the
    coding's settings (for the decoder before); ``make_coding(**overrides)``: the profile's
    coding with overrides, for the bit-for-bit comparison with the frozen decoder (made with
    the classification that decoder knows)."""
    frames, names, size = view.frames, view.names, view.projector_size
    frozen = frozen_settings(settings)
    before = graycode_before.GrayCode(**frozen)
    same_rule = {"classification": frozen.get("classification", "robust")}
    shadow_dn = view.coding.shadow_threshold * full_scale(frames[names.index("white")],
                                                          view.coding.bit_depth)
    sides = {
        "dotshell": lambda: view.coding.decode(frames, size),
        "opencv_lit_raster": peer.time_once,
        "numpy_integer": lambda: numpy_gray.decode(frames, names, size, shadow_dn),
        "dotshell_no_refine": lambda: integer_coding.decode(frames, size),
        "dotshell_before": lambda: before.decode(frames, size),
    }
    runs: dict[str, list[float]] = {k: [] for k in sides}
    keys = list(sides)
    for k in ("dotshell", "dotshell_no_refine"):  # untimed: compiled passes loaded or compiled
        sides[k]()
    for r in range(repeats):
        for k in keys[r % len(keys):] + keys[:r % len(keys)]:
            if k == "opencv_lit_raster":
                runs[k].append(sides[k]())
            else:
                s, _ = _timed(sides[k])
                runs[k].append(s)
    out: dict[str, Any] = {k: min_median(v) for k, v in runs.items()}
    out["identical_to_before"] = {
        "integer": _identical(
            make_coding(subpixel=False, **same_rule).decode(frames, size),
            graycode_before.GrayCode(**{**frozen, "subpixel": False}).decode(frames, size)),
        "subpixel": _identical(make_coding(**same_rule).decode(frames, size),
                               before.decode(frames, size))}
    ours = integer_coding.decode(frames, size)
    out["numpy_agreement"] = _numpy_agreement(ours, numpy_gray.decode(frames, names, size,
                                                                      shadow_dn))
    out["opencv_agreement"] = _opencv_agreement(ours, peer.finish(), size)
    out["opencv_version"] = str(peer.info["cv2_version"])
    out["lit_px"] = int(peer.info["lit"])
    out["repeats"] = repeats
    stats = ("min", "median")
    out["opencv_over_dotshell"] = {s: out["opencv_lit_raster"][s] / out["dotshell"][s]
                                   for s in stats}
    out["dotshell_over_numpy"] = {s: out["dotshell"][s] / out["numpy_integer"][s] for s in stats}
    out["before_over_dotshell"] = {s: out["dotshell_before"][s] / out["dotshell"][s]
                                   for s in stats}
    out["refine_s"] = out["dotshell"]["median"] - out["dotshell_no_refine"]["median"]
    return out


def _identical(ours: Correspondence, theirs: Correspondence) -> dict[str, Any]:
    """Pixels where two decodes differ (codes or coordinates, NaN equal to NaN), and whether
    the masks and statistics are the same."""
    differ = ours.valid != theirs.valid
    for axis in ("column", "row"):
        a, b = getattr(ours, axis), getattr(theirs, axis)
        if a is not None and b is not None:
            differ |= ~((a == b) | (np.isnan(a) & np.isnan(b)))
    return {"differing_px": int(differ.sum()), "same_stats": ours.stats == theirs.stats,
            "same_reasons": bool(np.array_equal(ours.reason, theirs.reason))}


def _numpy_agreement(ours: Correspondence, codes: numpy_gray.IntegerCodes) -> dict[str, Any]:
    both = ours.valid & codes.valid
    same = (ours.column[both] == codes.column[both]) & (ours.row[both] == codes.row[both])
    return {"dotshell_valid": int(ours.valid.sum()), "numpy_valid": int(codes.valid.sum()),
            "both": int(both.sum()), "equal_pct": 100.0 * float(same.mean())}


def _opencv_agreement(ours: Correspondence, peer: dict[str, np.ndarray],
                      size: tuple[int, int]) -> dict[str, Any]:
    """OpenCV decodes the raw code value, dotshell the centred one: OpenCV column −
    ``code_offset`` is compared with dotshell's integer column. Rows are not compared (OpenCV
    flags decoded rows past its height as errors; our row code is centred)."""
    xs, ys, ok = peer["xs"], peer["ys"], ~peer["error"]
    both = ok & ours.valid[ys, xs]
    theirs = peer["col"][both].astype(np.int64) - code_offset(size[0])
    equal = ours.column[ys[both], xs[both]].astype(np.int64) == theirs
    return {"opencv_decoded": int(ok.sum()), "dotshell_decoded_of_lit": int(
        ours.valid[ys, xs].sum()), "both": int(both.sum()),
        "column_equal_pct": 100.0 * float(equal.mean()) if both.any() else None}


def print_decoders(d: dict[str, Any], baseline: dict[str, Any]) -> None:
    print(f"\n== 3. decoders on the same view, interleaved (min / median of {d['repeats']}; "
          f"ms per view) ==")
    rows = (("dotshell decode (robust, sub-pixel)", "dotshell"),
            ("the same decoder before issue 16 part 2 (frozen)", "dotshell_before"),
            (f"OpenCV {d['opencv_version']} getProjPixel, {d['lit_px']} lit px, raster order",
             "opencv_lit_raster"),
            ("plain numpy integer gray decode", "numpy_integer"),
            ("dotshell decode with subpixel = false", "dotshell_no_refine"))
    for label, key in rows:
        m = d[key]
        print(f"  {label:62s} {m['min'] * 1e3:9.1f} / {m['median'] * 1e3:9.1f}")
    before = baseline.get("refine_ms")
    print(f"  sub-pixel refinement (difference of the medians) {d['refine_s'] * 1e3:9.1f}"
          + (f"   (baseline {before:.0f})" if before else ""))
    for key, what in (("before_over_dotshell", "before time / dotshell time"),
                      ("opencv_over_dotshell", "OpenCV time / dotshell time"),
                      ("dotshell_over_numpy", "dotshell time / numpy time")):
        r, before = d[key], baseline.get(key, {}).get("median")
        print(f"  {what:40s} {r['min']:7.2f}x min {r['median']:7.2f}x median"
              + (f"   (baseline {before:.2f}x median)" if before else ""))
    for key, ident in d["identical_to_before"].items():
        print(f"  dotshell vs before ({key}): {ident['differing_px']} px differ, statistics "
              f"{'equal' if ident['same_stats'] else 'DIFFERENT'}, reasons "
              f"{'equal' if ident['same_reasons'] else 'DIFFERENT'}")
    a = d["numpy_agreement"]
    print(f"  numpy integer codes == dotshell's (subpixel = false) on {a['equal_pct']:.4f} % of "
          f"{a['both']} px valid in both (dotshell {a['dotshell_valid']}, numpy "
          f"{a['numpy_valid']})")
    o = d["opencv_agreement"]
    if o["column_equal_pct"] is not None:
        print(f"  OpenCV column == dotshell's integer column on {o['column_equal_pct']:.3f} % of "
              f"{o['both']} px decoded by both (OpenCV {o['opencv_decoded']} of the lit pixels, "
              f"dotshell {o['dotshell_decoded_of_lit']})")
