"""The coding backends besides the gray code — xor02, xor04, graycode-phase — and what all
codings share: names, pattern sequences, exact decoding of the projected images, float32
(PDI) frames, non-power-of-two projectors, sub-pixel precision on the synthetic camera."""

from __future__ import annotations

import numpy as np
import pytest

from dotshell.coding import PatternCoding
from dotshell_codings import dotshell_codings
from dotshell_codings.graycode import code_offset
from dotshell_codings.phaseshift import phase_and_amplitude, unwrap
from test_graycode import PROJ, errors, make_coding, render, rms

NAMES = ("graycode", "xor02", "xor04", "graycode-phase")


def test_backends_registered():
    assert {b.name for b in dotshell_codings()} == set(NAMES)
    for name in NAMES:
        assert isinstance(make_coding(name), PatternCoding)


@pytest.mark.parametrize("name, count", [("graycode", 42), ("xor02", 42), ("xor04", 42),
                                         ("graycode-phase", 2 + 2 * 8 + 2 * 8 + 2 * 4)])
def test_pattern_counts_and_names(name, count):
    c = make_coding(name)
    pats = c.patterns(PROJ)
    names = [p.name for p in pats]
    assert len(pats) == count and len(set(names)) == count and names == c.frame_names(PROJ)
    assert names[:2] == ["white", "black"]
    for p in pats:
        assert p.image.dtype == np.uint8 and p.image.shape == (768, 1024)
    if name == "graycode-phase":
        # period 16: drop_low_bits = 2 (finest gray stripe 4 px): 8 column and 8 row bits
        assert names[2:4] == ["col_00", "col_00_inv"] and names[-4:] == [f"row_ps_{k}" for k in range(4)]
        assert len(make_coding(name, phase_steps=8, axes="columns").patterns(PROJ)) == 2 + 16 + 8


@pytest.mark.parametrize("name, widest", [("xor02", 2), ("xor04", 4)])
def test_xor_patterns_are_all_high_frequency(name, widest):
    """Every XOR pattern's stripes are at most the base's width (the gray code's MSB stripe is
    512 px); at least one is exactly the base (projected as it is)."""
    pats = make_coding(name, axes="columns").patterns((1000, 4))[2::2]
    runs = []
    for p in pats:
        row = p.image[0].astype(int)
        edges = np.flatnonzero(np.diff(row)) + 1
        inner = np.diff(edges)  # complete stripes (the two ends are cut by the border)
        runs.append(inner.max())
    assert max(runs) == widest and min(runs) >= 1


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("proj", [(1000, 700), (912, 1140)])
def test_identity_decode_all(name, proj):
    c = make_coding(name)
    r = c.decode([p.image for p in c.patterns(proj)], proj)
    w, h = proj
    tol = 0.02 if name == "graycode-phase" else 0.0  # 8-bit sinusoids
    assert r.valid.all()
    assert np.abs(r.column - np.arange(w)[None]).max() <= tol
    assert np.abs(r.row - np.arange(h)[:, None]).max() <= tol


@pytest.mark.parametrize("name", NAMES)
def test_float32_frames(name):
    """Float32 frames (a camera or a user's images in floating point; PDI differences stay in
    the camera's integer type, dotshell.pipeline.pdi) have no fixed range: full scale is the
    white frame's 99.5th percentile."""
    c = make_coding(name, axes="columns")
    proj = (1000, 40)
    frames = [p.image.astype(np.float32) * 0.37 + 2.0 for p in c.patterns(proj)]
    frames[0][0, :5] = 1e6  # a few hot pixels do not set the scale
    r = c.decode(frames, proj)
    assert r.valid[1:].all() and r.row is None
    assert np.abs(r.column[1:] - np.arange(1000)[None]).max() <= 0.02


@pytest.mark.parametrize("name", ["xor02", "xor04", "graycode-phase"])
def test_wrong_frame_count(name):
    c = make_coding(name)
    with pytest.raises(ValueError, match="expects"):
        c.decode([p.image for p in c.patterns(PROJ)][:-1], PROJ)


# ---- synthetic camera: precision ------------------------------------------------------------

@pytest.mark.parametrize("name, proj, max_rms, min_valid, max_wrong", [
    # valid share of the whole image (4-px border excluded: at most 0.912); measured figures:
    ("graycode", (1000, 700), 0.06, 0.9, 0.001),        # 0.036 px, 0.91, 0
    ("xor04", (1000, 700), 0.3, 0.7, 0.01),             # 0.23 px, 0.77, 0.3 %
    ("xor02", (912, 1140), 0.3, 0.5, 0.08),             # 0.21 px, 0.60, 5 %
    ("graycode-phase", (1000, 700), 0.06, 0.9, 0.001),  # 0.044 px, 0.91, 0
    ("graycode-phase", (912, 1140), 0.06, 0.9, 0.001)])
def test_synthetic_precision(name, proj, max_rms, min_valid, max_wrong):
    """XOR codes lose pixels and sub-pixel precision in their narrow stripes (1-2 projector
    px = 1.4-2.9 camera px here); the wrong ones are integer +-1 steps (< 1.5 px)."""
    c = make_coding(name)
    frames, u, v = render(c, proj=proj, cam=(200, 160), seed=7)
    r = c.decode(frames, proj)
    m, ec, er = errors(r, u, v)
    assert m.mean() > min_valid
    wrong = (np.abs(ec) > 1) | (np.abs(er) > 1)
    assert wrong.mean() <= max_wrong
    assert np.mean((np.abs(ec) > 2) | (np.abs(er) > 2)) < 0.002
    good = ~wrong
    assert rms(ec[good]) < max_rms and rms(er[good]) < max_rms


def test_phase_steps_8_more_precise_under_noise():
    out = []
    for n in (4, 8):
        c = make_coding("graycode-phase", phase_steps=n, axes="columns")
        frames, u, v = render(c, cam=(200, 160), noise=4.0, seed=8)
        r = c.decode(frames, PROJ)
        m = r.valid.copy()
        m[:4], m[-4:], m[:, :4], m[:, -4:] = False, False, False, False
        out.append(rms(r.column[m] - u[m]))
    assert out[1] < 0.85 * out[0]  # ~1/sqrt(2) expected


def test_unwrap_robust_at_period_boundaries():
    """The coarse (gray) estimate may be off by up to 0.375 period on either side of a period
    boundary without changing the unwrapped coordinate."""
    period, origin = 16, -code_offset(1000) - 0.5
    x = np.linspace(100.0, 900.0, 4001)
    phi = np.mod(2 * np.pi * (x - origin) / period, 2 * np.pi)
    for err in (-0.375 * period, -3.0, 0.0, 3.0, 0.375 * period):
        u, mismatch = unwrap(phi, x + err, origin, period)
        assert np.abs(u - x).max() < 1e-3 and np.abs(mismatch - abs(err)).max() < 1e-3
    frames = [10 + 5 * np.cos(np.array([[0.3]]) - 2 * np.pi * k / 4) for k in range(4)]
    p, a = phase_and_amplitude(frames)
    assert p[0, 0] == pytest.approx(0.3, abs=1e-5) and a[0, 0] == pytest.approx(5.0, abs=1e-4)


def test_phase_modulation_threshold():
    """Sinusoids swinging 10 % of white - black are low_modulation (default 0.2)."""
    c = make_coding("graycode-phase", axes="columns")
    proj = (1000, 40)
    frames = [p.image.astype(np.float32) for p in c.patterns(proj)]
    n = len(frames)
    for k in range(n - 4, n):
        frames[k] = 127.5 + 0.1 * (frames[k] - 127.5)
    r = c.decode(frames, proj)
    assert not r.valid.any() and r.stats["low_modulation"] == r.stats["pixels"]
