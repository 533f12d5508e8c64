"""Robust bit classification (plugins/dotshell_codings/robust.py) and the codings under global
light, on the synthetic camera of tests/test_graycode.py (no simulator).

Scenes (240x180 camera, 0.7 projector px per camera px, 8-bit unless said):
* long-range global light: direct 30 %, global 70 % of the light, 80 % of the global light
  coming from 150 projector px away (an inter-reflection) and spread by 12 camera px;
* PDI-like: 12-bit frames of a translucent body, direct 5 % and depolarized global 95 %,
  shot + read noise; PDI frames |I∥ − I⊥| as float32, or the plain frames without analyzer.

Run ``python tests/test_codings_robust.py`` to print the figures table of docs/codings.md.
"""

from __future__ import annotations

import numpy as np
import pytest

from dotshell_codings.robust import direct_global, full_scale, noise_sigma, robust_bits
from test_graycode import PROJ, make_coding, render, render_pdi, rms

LONG_RANGE = dict(direct=0.3, global_weight=0.7, global_shift=150.0, global_far=0.8)


def outcome(coding, frames, u, v, margin: int = 4) -> dict:
    """Shares of the camera's inner pixels: valid, wrong (|decoded − true| > 1 px on either
    axis), uncertain, low_contrast; sub-pixel RMS (px) of the columns that are not wrong."""
    c = coding.decode(frames, PROJ)
    m = c.valid.copy()
    m[:margin], m[-margin:], m[:, :margin], m[:, -margin:] = False, False, False, False
    n = m[margin:-margin, margin:-margin].size
    e = np.maximum(np.abs(c.column - u), np.abs(c.row - v))[m]
    good = e <= 1.0
    ec = (c.column - u)[m][good]
    s = c.stats
    assert s["pixels"] == sum(s[k] for k in ("decoded", "shadow", "low_contrast", "uncertain",
                                             "out_of_range", "low_modulation",
                                             "phase_inconsistent") if k in s)
    return {"valid": m.sum() / n, "wrong": (~good).sum() / n,
            "uncertain": s["uncertain"] / s["pixels"], "low_contrast": s["low_contrast"] / s["pixels"],
            "rms": rms(ec) if ec.size else float("nan")}


_FRAMES: dict = {}


def run(name: str, scene: str, cam=(240, 180), **settings) -> dict:
    """Decode ``scene`` with backend ``name``; frames are shared by settings that do not change
    the patterns (the classification)."""
    coding = make_coding(name, **settings)
    key = (name, scene, cam, tuple(sorted((k, v) for k, v in settings.items()
                                          if k != "classification")))
    if key not in _FRAMES:
        _FRAMES[key] = _render(coding, scene, cam)
    return outcome(coding, *_FRAMES[key])


def _render(coding, scene: str, cam):
    if scene == "clean":
        frames, u, v = render(coding, cam=cam)
    elif scene == "long_range":
        frames, u, v = render(coding, cam=cam, **LONG_RANGE)
    else:
        frames, u, v = render_pdi(coding, pdi=scene == "pdi", cam=cam)
    return frames, u, v


# ---- pure functions -------------------------------------------------------------------------

def test_direct_global_separation_formulas():
    ld_true, lg_true = np.float32(40.0), np.float32(100.0)
    for b in (0.0, 0.1):
        # lit: L_d + b... Nayar's model for a half-lit high-frequency pattern: lit pixels see
        # L_d + (1 + b) L_g / 2, unlit ones b L_d + (1 + b) L_g / 2
        lit = ld_true + (1 + b) * lg_true / 2
        unlit = b * ld_true + (1 + b) * lg_true / 2
        frames = [np.full((2, 2), x, np.float32) for x in (lit, unlit, unlit, lit)]
        ld, lg = direct_global(frames, b)
        assert np.allclose(ld, ld_true, rtol=1e-5) and np.allclose(lg, lg_true, rtol=1e-5)
    # no global light and noise putting L_min below b L_max: L_g = 0, L_d = L_max
    ld, lg = direct_global([np.full((1, 1), 50.0, np.float32), np.full((1, 1), 1.0, np.float32)], 0.1)
    assert lg[0, 0] == 0.0 and ld[0, 0] == 50.0
    with pytest.raises(ValueError):
        direct_global([], 0.0)


def test_robust_rule_branches():
    # columns: L_d < m | L_d > L_g (p>i, p<i) | interval 0 | interval 1 | in between
    p = np.array([90, 60, 20, 10, 80, 50], np.float32)
    q = np.array([10, 20, 60, 90, 5, 45], np.float32)
    ld = np.array([3, 50, 50, 30, 30, 30], np.float32)
    lg = np.array([0, 20, 20, 70, 70, 70], np.float32)
    bit, unc = robust_bits(p, q, ld, lg, 5.0)
    assert unc.tolist() == [True, False, False, False, False, True]
    assert bit.tolist() == [False, True, False, False, True, False]


def test_full_scale_and_noise_floor():
    white = np.full((10, 10), 3000, np.uint16)
    assert full_scale(white) == 4095.0 and full_scale(white.astype(np.uint8)) == 255.0
    assert full_scale(white, bit_depth=14) == 16383.0
    f = np.linspace(0, 200, 1000, dtype=np.float32).reshape(10, 100)
    assert full_scale(f) == pytest.approx(np.percentile(f, 99.5))
    rng = np.random.default_rng(1)
    black = (8 + rng.normal(0, 3.0, (200, 200))).astype(np.float32)
    assert 2.85 < noise_sigma(black) < 3.15
    # integer frames: the histogram medians give exactly the float path's value
    for shape, dtype, top in (((200, 200), np.uint16, 4095), ((7, 8), np.uint8, 255),
                              ((9, 2), np.uint16, 65535), ((40, 41), np.int32, 30)):
        for seed in range(5):
            ints = np.random.default_rng(seed).integers(0, top + 1, shape).astype(dtype)
            assert noise_sigma(ints) == noise_sigma(ints.astype(np.float32))


def test_robust_needs_inverse():
    g = make_coding("graycode", inverse=False)  # default adaptive: falls back to contrast
    assert g.classification == "contrast"
    assert make_coding("graycode").classification == "adaptive"


# ---- codings under global light ---------------------------------------------------------------

def test_clean_scene_unchanged_by_robust_classification():
    contrast, robust = (run("graycode", "clean", classification="contrast"),
                        run("graycode", "clean", classification="robust"))
    for r in (contrast, robust):
        assert r["valid"] > 0.99 and r["wrong"] < 1e-3 and r["rms"] < 0.06


def test_long_range_global_light_contrast_vs_robust_vs_xor():
    """Long-range global light (70 % of the light, mostly from 150 px away) flips the
    low-frequency gray bits: plain thresholding decodes wrong codes. The robust rule marks
    them uncertain instead; the XOR-04 code (all patterns high-frequency) decodes them."""
    gray = run("graycode", "long_range", classification="contrast")
    robust = run("graycode", "long_range", classification="robust")
    xor = run("xor04", "long_range")
    xor_contrast = run("xor04", "long_range", classification="contrast")
    assert gray["wrong"] > 0.2                       # measured 0.43: every decoded pixel wrong
    assert robust["wrong"] < 0.01 and robust["uncertain"] > 0.5   # measured 0, 1.00
    assert xor["wrong"] < 0.05 and xor["valid"] > 0.6             # measured 0.02, 0.84
    assert xor["wrong"] < 0.1 * gray["wrong"] and robust["wrong"] < 0.1 * gray["wrong"]
    # XOR with the plain white-relative contrast test: no wrong codes, but few pixels pass it
    assert xor_contrast["wrong"] < 0.01 and xor_contrast["valid"] < xor["valid"]


def test_pdi_like_low_contrast_float32():
    """Direct light 5 % of full scale, noisy, float32 PDI frames: decoded; the same scene
    without the analyzer (global light 95 %) is rejected, not decoded wrong."""
    contrast = run("graycode", "pdi", classification="contrast")
    robust = run("graycode", "pdi", classification="robust")
    for r in (contrast, robust):                      # measured 0.95 / 0.98 valid, 0.6 / 1.0 %
        assert r["valid"] > 0.9 and r["wrong"] < 0.02 and r["rms"] < 0.3
    plain = run("graycode", "no_pdi", classification="contrast")
    plain_robust = run("graycode", "no_pdi", classification="robust")
    assert plain["valid"] < 0.01 and plain["low_contrast"] > 0.95
    assert plain_robust["valid"] < 0.01 and plain_robust["uncertain"] > 0.95


def figures() -> None:
    rows = [(name, {"classification": c}) for name in ("graycode", "xor02", "xor04",
                                                       "graycode-phase")
            for c in ("contrast", "robust", "adaptive")] + [("graycode-phase",
                                                             {"phase_steps": 8})]
    print("| scene | coding | settings | valid | wrong (>1 px) | uncertain | low_contrast | RMS col px |")
    print("|---|---|---|---|---|---|---|---|")
    for scene in ("clean", "long_range", "pdi", "no_pdi"):
        for name, kw in rows:
            r = run(name, scene, **kw)
            print(f"| {scene} | {name} | {kw} | {r['valid']:.3f} | {r['wrong']:.4f} | "
                  f"{r['uncertain']:.3f} | {r['low_contrast']:.3f} | {r['rms']:.3f} |")


if __name__ == "__main__":
    figures()
