"""The compiled gray-code decoder against the decoder before issue 16 part 2, frozen in
``benchmarks/graycode_before.py``: the same integer codes, masks, reasons and statistics, bit for
bit, on synthetic scenes and on the simulated reference bench at reduced resolution, for every
classification and the settings that change the arithmetic (inverses, drop_low_bits, float32
frames, columns only, XOR codes, stripes across the image). The sub-pixel coordinates come out
identical too (same float32/float64 arithmetic), which the tests also check.

The same comparison runs on the full-resolution bench frames in ``make bench`` (section 3).
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from dotshell.coding import Correspondence
from dotshell_codings.graycode import GrayCode, as_stack
from dotshell_codings.xor import XorCode
from test_graycode import PROJ, _turned, render, render_pdi

_BEFORE = Path(__file__).resolve().parents[1] / "benchmarks" / "graycode_before.py"
_spec = importlib.util.spec_from_file_location("graycode_before", _BEFORE)
before = sys.modules.setdefault("graycode_before", importlib.util.module_from_spec(_spec))
_spec.loader.exec_module(before)


def assert_same(new: Correspondence, old: Correspondence) -> None:
    assert new.stats == old.stats
    assert np.array_equal(new.valid, old.valid)
    assert np.array_equal(new.reason, old.reason) and new.reason_names == old.reason_names
    for axis in ("column", "row"):
        a, b = getattr(new, axis), getattr(old, axis)
        assert (a is None) == (b is None)
        if a is not None:
            assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True), axis


def both(cls_new, cls_old, frames, proj=PROJ, **settings):
    # the frozen decoder has no adaptive classification (robust plus rescued pixels, tested in
    # tests/test_decode_adaptive.py): robust, the default, is asked
    settings.setdefault("classification", "robust")
    for subpixel in (False, True):
        new = cls_new(subpixel=subpixel, **settings).decode(frames, proj)
        old = cls_old(subpixel=subpixel, **settings).decode(frames, proj)
        assert_same(new, old)
        assert new.stats["decoded"] > 0.3 * new.stats["pixels"]
    return new


@pytest.mark.parametrize("settings, scene", [
    ({}, {"noise": 3.0, "blur": 1.2}),
    ({"classification": "contrast"}, {"noise": 3.0}),
    ({"inverse": False}, {}),
    ({"drop_low_bits": 1}, {"noise": 2.0}),
    ({"axes": "columns", "high_frequency_pairs": 4}, {"global_weight": 0.6, "direct": 0.5}),
    ({"centred": False, "black_level": 0.05}, {"dtype": np.uint16, "peak": 3000.0,
                                                "noise": 6.0}),
], ids=["robust", "contrast", "no-inverse", "drop-1", "columns-global", "uint16-black-level"])
def test_same_as_before_on_synthetic_scenes(settings, scene):
    frames, _, _ = render(GrayCode(**settings), cam=(200, 160), **scene)
    both(GrayCode, before.GrayCode, frames, **settings)


def test_same_as_before_on_float_pdi_frames_and_stripes_at_45_degrees():
    frames, _, _ = render_pdi(GrayCode(), cam=(200, 160))
    both(GrayCode, before.GrayCode, frames)
    frames, _, _ = render(GrayCode(), cam=(200, 200), mapping=_turned, noise=2.0)
    both(GrayCode, before.GrayCode, frames)


@pytest.mark.parametrize("base", [2, 4])
def test_same_as_before_for_xor_codes(base):
    frames, _, _ = render(XorCode(base_stripe_px=base), cam=(200, 160), noise=2.0, blur=1.2)
    both(lambda **s: XorCode(base_stripe_px=base, **s),
         lambda **s: before.XorCode(base_stripe_px=base, **s), frames)


def test_same_as_before_on_the_simulated_bench(sim_bench_view):
    """The reference bench (metal cylinder, 12-bit camera) at 320x256."""
    frames, proj, settings = sim_bench_view
    new = both(GrayCode, before.GrayCode, frames, proj, **settings)
    assert new.stats["refined_column"] > 0.9 * new.stats["decoded"]


@pytest.fixture(scope="module")
def sim_bench_view():
    sys.path.insert(0, str(_BEFORE.parent))
    try:
        from bench_profile import load_bench_profile
    finally:
        sys.path.remove(str(_BEFORE.parent))
    from dotshell.plugins import get_plugin_manager
    from dotshell.rig.assembly import Rig

    pm = get_plugin_manager()
    profile = load_bench_profile(pm, quick=True)
    # the frozen decoder has no adaptive classification (robust plus rescued pixels, tested in
    # tests/test_decode_adaptive.py): its settings are left out, robust is asked
    settings = {k: v for k, v in profile.role("coding")["settings"].items()
                if k not in ("subpixel", "adaptive_sigmas", "adaptive_edge_ratio",
                             "adaptive_code_steps")}
    settings["classification"] = "robust"
    coding = GrayCode(**settings)
    with Rig(profile, pm) as rig:
        rig.camera.set_exposure(profile.data["scan"]["exposure_ms"])
        frames = []
        for p in coding.patterns(rig.projector.resolution):
            rig.projector.show(p.image)
            frames.append(rig.camera.capture())
        proj = tuple(rig.projector.resolution)
    return frames, proj, settings


def test_frames_of_one_array_are_decoded_in_place():
    """Frames read as one stack and split (as a run's frame stack is) are not copied."""
    stack = np.arange(4 * 3 * 5, dtype=np.uint16).reshape(4, 3, 5)
    view = as_stack(list(stack))
    assert np.shares_memory(view, stack) and np.array_equal(view, stack)
    separate = [f.copy() for f in stack]
    copied = as_stack(separate)
    assert not np.shares_memory(copied, separate[0]) and np.array_equal(copied, stack)
    with pytest.raises(ValueError, match="one shape"):
        as_stack([stack[0], stack[1, :2]])


@pytest.mark.parametrize("threads", [1, 3, 7])
def test_the_one_pass_decoder_joins_its_bands_as_one_scan(threads, monkeypatch):
    """The one-pass decoder (a band of rows per thread, joined afterwards) gives the frozen
    decoder's result bit for bit however many bands the view is cut into, also when the
    stripes lie the other way across the image than their projector axis suggests (the camera
    turned by 90°: both axes are refined again the other way)."""
    from dotshell.runtime import parallel
    from dotshell_codings import kernels

    redone = []
    centres = kernels.block_centres
    monkeypatch.setattr(kernels, "block_centres",
                        lambda *a: redone.append(a[-1] - a[-2]) or centres(*a))
    frames, _, _ = render(GrayCode(), cam=(200, 160), noise=3.0, blur=1.2)
    turned = [np.ascontiguousarray(f.T) for f in frames]
    with parallel.threads(threads):
        assert len(parallel.bands(len(frames[0]))) - 1 == threads
        both(GrayCode, before.GrayCode, frames)
        assert not redone
        both(GrayCode, before.GrayCode, turned)
    assert sum(redone) == 2 * turned[0].shape[0]  # both axes, every row


@pytest.mark.parametrize("shape", [(6, 9), (5, 1), (4, 2)])
def test_the_needed_runs_are_the_lit_pixels_and_their_shadow_neighbours(shape):
    """The runs of a row whose bits are classified (``kernels._needed``, the row's and its
    neighbours' shadow tested in loops without branches) are the pixels that are lit or have a
    lit 4-neighbour, borders included, on random shadow (NaN range counts as shadow)."""
    from dotshell_codings import kernels

    h, w = shape
    rng = np.random.default_rng(7)
    thr = np.float32(10.0)
    for _ in range(20):
        white = rng.integers(0, 20, (h, w)).astype(np.float32)
        white[rng.random((h, w)) < 0.1] = np.nan
        stack = np.stack([white, np.zeros((h, w), np.float32)])
        r = np.nan_to_num(white, nan=0.0)
        lit = ~(r < thr)
        grown = lit.copy()
        grown[:, 1:] |= lit[:, :-1]
        grown[:, :-1] |= lit[:, 1:]
        grown[1:] |= lit[:-1]
        grown[:-1] |= lit[1:]
        spans = np.empty(w + 2, np.int64)
        for y in range(h):
            n = kernels._needed(stack, y, thr, ~lit[y], spans)
            got = np.zeros(w, bool)
            for s in range(n):
                got[spans[2 * s]:spans[2 * s + 1]] = True
            assert np.array_equal(got, grown[y]), (y, lit)


@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_two_robust_bits_a_pass_decide_as_one_at_a_time(dtype):
    """``kernels._robust_two`` (two pattern/inverse pairs in one loop) sets the same value and
    weak bits as ``kernels._robust`` once per pair, ties and the rule's boundaries included."""
    from dotshell_codings import kernels

    rng = np.random.default_rng(11)
    n = 4000
    p, q, p2, q2 = (rng.integers(0, 12, n).astype(dtype) for _ in range(4))
    black = rng.integers(0, 3, n).astype(np.float32)
    ld = rng.integers(0, 10, n).astype(np.float32)
    lg = rng.integers(0, 10, n).astype(np.float32)
    m = np.float32(3.0)
    start = rng.integers(0, 1 << 20, n).astype(np.uint32)
    val1, wk1, val2, wk2 = start.copy(), start.copy() ^ 5, start.copy(), start.copy() ^ 5
    shift = np.uint32(7)
    kernels._robust(p, q, black, ld, lg, m, shift, val1, wk1)
    kernels._robust(p2, q2, black, ld, lg, m, np.uint32(6), val1, wk1)
    kernels._robust_two(p, q, p2, q2, black, ld, lg, m, shift, val2, wk2)
    assert np.array_equal(val1, val2) and np.array_equal(wk1, wk2)
    assert len(np.unique(val1 >> 6 & 3)) == 4 and len(np.unique(wk1 >> 6 & 3)) == 4
