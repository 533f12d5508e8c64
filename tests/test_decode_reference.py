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
    # tests/test_decode_adaptive.py; the gray code's default now): its default, robust, is asked
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
                if k not in ("subpixel", "adaptive_sigmas", "adaptive_edge_ratio")}
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
