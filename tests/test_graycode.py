"""Tests of the gray-code coding plugin (plugins/dotshell_codings) on synthetic camera frames.

The synthetic camera sees the projector through a known smooth mapping (no simulator): each
camera pixel's footprint is supersampled, the projected image is looked up at every sample
(projector pixel c spans [c - 0.5, c + 0.5]), then defocus (Gaussian blur), albedo, noise and
8-bit quantization are applied.

Run ``python tests/test_graycode.py`` to print the accuracy and timing figures.
"""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from dotshell.backends import Backend
from dotshell.coding import Correspondence, PatternCoding
from dotshell.settings import validate_settings
from dotshell_codings import dotshell_codings
from dotshell_codings.graycode import SETTINGS_SCHEMA, GrayCode, code_offset

PROJ = (1024, 768)


def backend(name: str = "graycode") -> Backend:
    (found,) = [b for b in dotshell_codings() if b.name == name]
    return found


def make_coding(name: str, **settings):
    """A coding built the way the pipeline builds it: settings validated against the schema."""
    b = backend(name)
    full = validate_settings(b.settings_schema, settings, "test")
    return b.factory(settings=full, context=None)


def make(**settings) -> GrayCode:
    return make_coding("graycode", **settings)


# ---- synthetic camera -----------------------------------------------------------------------

def camera_mapping(xs: np.ndarray, ys: np.ndarray, scale: float = 0.7):
    """True projector (column, row) seen at camera position (xs, ys); smooth, ~scale projector
    px per camera px, with some shear and waviness."""
    u = 200.3 + scale * xs + 0.05 * ys + 3.0 * np.sin(2 * np.pi * ys / 97.0 + 0.3) \
        + 2.0 * np.sin(2 * np.pi * xs / 151.0)
    v = 150.7 + scale * ys - 0.04 * xs + 2.5 * np.sin(2 * np.pi * xs / 83.0)
    return u, v


def _samples(cam, ss, mapping, scale, proj):
    """Supersampled projector indices of every camera pixel's footprint."""
    cw, ch = cam
    off = (np.arange(ss) + 0.5) / ss - 0.5
    yy, xx = np.mgrid[0:ch, 0:cw].astype(np.float64)
    sx = (xx[:, :, None, None] + off[None, None, None, :]).reshape(ch, cw, -1)
    sy = (yy[:, :, None, None] + off[None, None, :, None]).reshape(ch, cw, -1)
    su, sv = mapping(sx, sy, scale) if mapping is camera_mapping else mapping(sx, sy)
    return xx, yy, su, sv


def _lookup(su, sv, proj, shift=0.0):
    pc = np.floor(su + shift + 0.5).astype(np.int64)
    pr = np.floor(sv + 0.5).astype(np.int64)
    inside = (pc >= 0) & (pc < proj[0]) & (pr >= 0) & (pr < proj[1])
    return np.clip(pc, 0, proj[0] - 1), np.clip(pr, 0, proj[1] - 1), inside


def light(coding, proj=PROJ, cam=(320, 240), ss: int = 4, blur: float = 0.8, scale: float = 0.7,
          mapping=camera_mapping, global_sigma: float = 0.0, global_shift: float = 0.0,
          global_far: float = 1.0):
    """Noise-free light fractions per pattern: (name, direct, global) images in [0, 1] before
    albedo, plus the camera grid and the true (column, row).

    direct: the pattern seen through the camera footprint, defocused by ``blur`` (camera px).
    global: the pattern spread by a Gaussian of ``global_sigma`` camera pixels (subsurface
    scattering); the share ``global_far`` of it comes from a region ``global_shift`` projector
    pixels away (long-range light: an inter-reflection, or light re-emerging far from where it
    entered). Under a high-frequency pattern it is 1/2 of its value under white.
    """
    xx, yy, su, sv = _samples(cam, ss, mapping, scale, proj)
    pc, pr, inside = _lookup(su, sv, proj)
    if global_sigma > 0:
        gc, gr, ginside = _lookup(su, sv, proj, global_shift)
    out = []
    for pat in coding.patterns(proj):
        img = pat.image.astype(np.float32) / 255.0
        f = (img[pr, pc] * inside).mean(axis=2).astype(np.float32)
        direct = cv2.GaussianBlur(f, (0, 0), blur) if blur > 0 else f
        glob = None
        if global_sigma > 0:
            g = (img[gr, gc] * ginside).mean(axis=2).astype(np.float32)
            if global_far < 1:
                g = global_far * g + (1 - global_far) * f
            glob = cv2.GaussianBlur(g, (0, 0), global_sigma, borderType=cv2.BORDER_REFLECT)
        out.append((pat.name, direct, glob))
    u, v = mapping(xx, yy, scale) if mapping is camera_mapping else mapping(xx, yy)
    return out, xx, yy, u, v


def render(coding: GrayCode, proj=PROJ, cam=(320, 240), ss: int = 4, blur: float = 0.8,
           noise: float = 1.0, seed: int = 0, scale: float = 0.7, mapping=camera_mapping,
           dtype=np.uint8, peak: float = 220.0, black_level: float = 8.0, shadow=None,
           low_contrast=None, direct: float = 1.0, global_weight: float = 0.0,
           global_sigma: float = 12.0, global_shift: float = 0.0, global_far: float = 1.0):
    """Frames for every pattern of ``coding``, the true (column, row) at pixel centres.

    Each frame is ``black_level + peak * albedo * (direct * D + global_weight * G)`` plus
    Gaussian noise, quantized to ``dtype`` (float32: not rounded). D and G as in
    :func:`light`; ``global_weight = 0`` (default) leaves the global light out."""
    rng = np.random.default_rng(seed)
    lights, xx, yy, u, v = light(coding, proj, cam, ss, blur, scale, mapping,
                                 global_sigma if global_weight > 0 else 0.0, global_shift,
                                 global_far)
    albedo = 0.75 + 0.2 * np.sin(xx / 40.0) * np.cos(yy / 55.0)
    frames = []
    for name, d, g in lights:
        f = d.astype(np.float64)
        if low_contrast is not None and name not in ("white", "black"):
            f[low_contrast] = 0.5 + 0.05 * (f[low_contrast] - 0.5)
        f = direct * f + (global_weight * g if g is not None else 0.0)
        f = black_level + peak * albedo * f
        if shadow is not None:
            f[shadow] = black_level
        f = f + rng.normal(0.0, noise, f.shape)
        if np.issubdtype(np.dtype(dtype), np.integer):
            f = np.clip(np.round(f), 0, np.iinfo(dtype).max)
        frames.append(f.astype(dtype))
    return frames, u, v


def render_pdi(coding, direct: float = 0.05, global_weight: float = 0.95, peak: float = 3000.0,
               read_noise: float = 4.0, e_per_dn: float = 2.5, seed: int = 0, pdi: bool = True,
               **kw):
    """12-bit camera frames of a translucent body through a polarizer/analyzer pair.

    The direct (surface) reflection keeps its polarization, the global (subsurface) light is
    depolarized: I∥ = direct + global/2, I⊥ = global/2 (plus black level, shot and read
    noise, 12-bit quantization each). ``pdi=True`` returns the float32 PDI frames |I∥ − I⊥|
    (the global light cancels, the direct signal is ``direct`` = a few % of full scale);
    ``pdi=False`` the plain uint16 frames without analyzer (I∥ + I⊥)."""
    rng = np.random.default_rng(seed)
    lights, xx, yy, u, v = light(coding, global_sigma=kw.pop("global_sigma", 12.0),
                                 global_shift=kw.pop("global_shift", 0.0), **kw)
    albedo = 0.75 + 0.2 * np.sin(xx / 40.0) * np.cos(yy / 55.0)

    def expose(signal):
        dn = 8.0 + peak * albedo * signal
        dn = dn + rng.normal(0.0, 1.0, dn.shape) * np.sqrt(read_noise ** 2 + dn / e_per_dn)
        return np.clip(np.round(dn), 0, 4095)

    frames = []
    for _, d, g in lights:
        par = expose(direct * d + 0.5 * global_weight * g)
        perp = expose(0.5 * global_weight * g)
        if pdi:
            frames.append(np.abs(par - perp).astype(np.float32))
        else:
            frames.append(expose(direct * d + global_weight * g).astype(np.uint16))
    return frames, u, v


def errors(c: Correspondence, u: np.ndarray, v: np.ndarray, margin: int = 4):
    """Error arrays of integer and sub-pixel decoding on valid pixels away from the border."""
    m = c.valid.copy()
    m[:margin], m[-margin:], m[:, :margin], m[:, -margin:] = False, False, False, False
    return m, c.column[m] - u[m], (c.row[m] - v[m]) if c.row is not None else None


def rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e ** 2)))


# ---- plugin and patterns --------------------------------------------------------------------

def test_backend_and_protocol():
    b = backend()
    assert isinstance(b, Backend) and b.name == "graycode"
    defaults = validate_settings(b.settings_schema, {}, "test")
    assert defaults["axes"] == "both" and defaults["inverse"] is True
    assert defaults["drop_low_bits"] == 0 and defaults["subpixel"] is True
    assert defaults["classification"] == "adaptive" and defaults["direct_min"] == 0.0
    assert isinstance(make(), PatternCoding)
    assert set(SETTINGS_SCHEMA) >= {"axes", "inverse", "min_contrast", "shadow_threshold",
                                    "drop_low_bits", "subpixel"}


def test_pattern_sequence_1024x768():
    pats = make().patterns(PROJ)
    names = [p.name for p in pats]
    assert len(pats) == 42 and len(set(names)) == 42
    assert names[:6] == ["white", "black", "col_00", "col_00_inv", "col_01", "col_01_inv"]
    assert names[22:24] == ["row_00", "row_00_inv"] and names[-1] == "row_09_inv"
    for p in pats:
        assert p.image.dtype == np.uint8 and p.image.shape == (768, 1024)
        assert set(np.unique(p.image)) <= {0, 255}
    assert [p.name for p in make(axes="columns").patterns(PROJ)][-1] == "col_09_inv"
    assert len(make(axes="columns").patterns(PROJ)) == 22
    assert len(make(inverse=False).patterns(PROJ)) == 22
    assert len(make(drop_low_bits=2).patterns(PROJ)) == 2 + 2 * 16
    assert make().frame_names(PROJ) == names


@pytest.mark.parametrize("size", [1000, 912, 1140, 700, 5])
def test_centred_code(size):
    """Column c carries Gray(c + (2^n - W)//2): the stripe structure is mirror-symmetric about
    the projector centre (for even (2^n - W)/2 exactly), adjacent columns differ in one bit."""
    proj = (size, 4)
    pats = make(axes="columns").patterns(proj)
    bits = np.array([p.image[0] // 255 for p in pats[2::2]])        # (n, W)
    n = bits.shape[0]
    assert n == int(np.ceil(np.log2(size)))
    assert np.all(np.abs(np.diff(bits.astype(int), axis=1)).sum(axis=0) == 1)
    g = (bits.astype(np.int64) << np.arange(n - 1, -1, -1)[:, None]).sum(axis=0)
    v = np.arange(size) + code_offset(size)
    assert np.array_equal(g, v ^ (v >> 1))
    if ((1 << n) - size) % 2 == 0:
        # reflected code: coarser bits mirror about the centre, the MSB inverts
        assert np.array_equal(bits[1:], bits[1:, ::-1]) and np.array_equal(bits[0], 1 - bits[0, ::-1])


# ---- exact decoding of the projected images themselves --------------------------------------

@pytest.mark.parametrize("proj, kw", [((1024, 768), {}), ((1000, 700), {}), ((912, 1140), {}),
                                      ((1000, 700), {"inverse": False}),
                                      ((912, 1140), {"subpixel": False})])
def test_identity_decode(proj, kw):
    g = make(**kw)
    c = g.decode([p.image for p in g.patterns(proj)], proj)
    w, h = proj
    assert c.valid.all() and c.column.dtype == np.float32
    assert np.array_equal(c.column, np.broadcast_to(np.arange(w, dtype=np.float32), (h, w)))
    assert np.array_equal(c.row, np.broadcast_to(np.arange(h, dtype=np.float32)[:, None], (h, w)))
    assert c.stats["decoded"] == w * h and c.stats["pixels"] == w * h


@pytest.mark.parametrize("proj, drop", [((1000, 700), 1), ((912, 1140), 3)])
def test_identity_drop_low_bits(proj, drop):
    g = make(drop_low_bits=drop, subpixel=False)
    c = g.decode([p.image for p in g.patterns(proj)], proj)
    w, h = proj
    assert c.valid.all()
    half = (1 << drop) / 2
    # integer estimate: centre of the decoded block (clipped to the projector)
    assert np.abs(c.column - np.arange(w)[None]).max() <= half
    assert np.abs(c.row - np.arange(h)[:, None]).max() <= half
    # with sub-pixel edges the blocks are interpolated back to full resolution
    c2 = make(drop_low_bits=drop).decode([p.image for p in g.patterns(proj)], proj)
    inner = np.abs(c2.column - np.arange(w)[None])[:, 2 << drop:-(2 << drop)]
    assert inner.max() < 1e-3


def test_uint16_and_columns_only():
    g = make(axes="columns")
    frames = [p.image.astype(np.uint16) * 16 for p in g.patterns((1000, 50))]  # 12-bit data
    c = g.decode(frames, (1000, 50))
    assert c.row is None and c.valid.all()
    assert np.array_equal(c.column[0], np.arange(1000, dtype=np.float32))


def test_wrong_frame_count():
    g = make()
    with pytest.raises(ValueError):
        g.decode([p.image for p in g.patterns(PROJ)][:-1], PROJ)
    with pytest.raises(ValueError):
        make(drop_low_bits=10).patterns(PROJ)


# ---- synthetic camera -----------------------------------------------------------------------

@pytest.fixture(scope="module")
def scene():
    g = make()
    ch, cw = 240, 320
    yy, xx = np.mgrid[0:ch, 0:cw]
    shadow = (xx > 250) & (yy > 180)
    low = (xx < 40) & (yy > 190)
    frames, u, v = render(g, ss=8, shadow=shadow, low_contrast=low)
    return g, frames, u, v, shadow, low


def _away_from(mask: np.ndarray, px: int = 4) -> np.ndarray:
    """Pixels farther than px from mask (defocus mixes the regions near its border)."""
    return ~cv2.dilate(mask.astype(np.uint8), np.ones((2 * px + 1, 2 * px + 1), np.uint8)).astype(bool)


def test_synthetic_decode_accuracy(scene):
    g, frames, u, v, shadow, low = scene
    keep = _away_from(shadow | low)
    c = g.decode(frames, PROJ)
    c.valid &= keep
    m, ec, er = errors(c, u, v)
    assert m.sum() > 0.99 * keep[4:-4, 4:-4].sum()
    ci = make(subpixel=False).decode(frames, PROJ)
    ci.valid &= keep
    mi, eci, eri = errors(ci, u, v)
    # integer decoding equals the rounded truth, except where the truth is so close to a stripe
    # boundary (0.5 mod 1) that the edge-localization noise (~0.02 px) decides either way
    for dec, true in ((ci.column[mi], u[mi]), (ci.row[mi], v[mi])):
        exact = dec == np.floor(true + 0.5)
        far = np.abs(true % 1.0 - 0.5) > 0.1
        assert exact[far].mean() >= 0.999 and exact.mean() >= 0.95
        assert np.abs(dec - true).max() < 0.5 + 0.15
    # sub-pixel: far below the integer quantization (~0.29 px RMS)
    assert rms(ec) < 0.1 and rms(er) < 0.1
    assert rms(ec) < 0.4 * rms(eci) and rms(er) < 0.4 * rms(eri)
    assert np.abs(ec).max() < 1.0 and np.abs(er).max() < 1.0
    assert c.stats["refined_column"] > 0.95 * c.stats["decoded"]
    c = g.decode(frames, PROJ)
    assert c.column.dtype == np.float32 and np.isnan(c.column[~c.valid]).all()
    assert np.isnan(c.row[~c.valid]).all()
    # near the masked regions (defocus mixes them in) errors stay within one projector pixel
    assert np.nanmax(np.abs(c.column - u)) < 1.5 and np.nanmax(np.abs(c.row - v)) < 1.5


def test_synthetic_masks(scene):
    g, frames, u, v, shadow, low = scene
    c = make(classification="contrast").decode(frames, PROJ)
    s = c.stats
    assert s["pixels"] == (s["decoded"] + s["shadow"] + s["low_contrast"] + s["uncertain"]
                           + s["out_of_range"]) and s["uncertain"] == 0
    assert not c.valid[shadow].any()
    assert s["shadow"] >= shadow.sum() and s["shadow"] < 1.3 * shadow.sum()
    inner = _away_from(~low, 2)  # the region less its blurred border
    assert not c.valid[inner].any() and s["low_contrast"] >= inner.sum()
    assert s["low_contrast"] < low.sum() + 0.02 * s["pixels"]


def test_synthetic_masks_robust(scene):
    """Robust classification: the low-contrast region (stripes swinging 5 % around half of
    white, which to the direct/global separation is strong global light, L_d << L_g) is
    uncertain, not low_contrast and not decoded; the shadow stays shadow; the rest decodes."""
    g, frames, u, v, shadow, low = scene
    c = make(classification="robust").decode(frames, PROJ)
    s = c.stats
    assert s["pixels"] == (s["decoded"] + s["shadow"] + s["low_contrast"] + s["uncertain"]
                           + s["out_of_range"]) and s["low_contrast"] == 0
    assert not c.valid[shadow].any() and s["shadow"] < 1.3 * shadow.sum()
    inner = _away_from(~low, 2)
    assert not c.valid[inner].any() and s["uncertain"] >= inner.sum()
    assert s["uncertain"] < low.sum() + 0.02 * s["pixels"]
    keep = _away_from(shadow | low)
    assert c.valid[keep].mean() > 0.99


def test_out_of_range():
    """A camera looking past the projector's right edge: decoded values beyond W are masked."""
    g = make(axes="columns")
    w = 1000  # 24 unused codes on each side of the centred code
    frames, u, v = render(g, proj=(w, 8), mapping=lambda x, y: (900.0 + 0.7 * x, 0 * y + 3.0),
                          cam=(320, 20), blur=0.6)
    c = g.decode(frames, (w, 8))
    past = u > w + 1
    assert not c.valid[past].any()
    # beyond the projector the image is dark: shadow, except that the stripe code does not
    # exist there either; both make the pixel invalid
    assert c.stats["shadow"] + c.stats["out_of_range"] >= past.sum()
    m = c.valid & (u < w - 2)
    assert m.sum() > 0 and np.abs(c.column[m] - u[m]).max() < 1.0
    # an impossible code (beyond the 1000 used columns) reported as out_of_range
    imgs = [p.image.copy() for p in g.patterns((w, 8))]
    n = (len(imgs) - 2) // 2
    code = 1023  # binary all ones -> Gray 1000000000
    gbits = [(code ^ (code >> 1)) >> (n - 1 - i) & 1 for i in range(n)]
    for i, bit in enumerate(gbits):
        imgs[2 + 2 * i][:, 0] = 255 * bit
        imgs[3 + 2 * i][:, 0] = 255 * (1 - bit)
    c = g.decode(imgs, (w, 8))
    assert not c.valid[:, 0].any() and c.stats["out_of_range"] == 8


@pytest.mark.parametrize("proj", [(1000, 700), (912, 1140)])
def test_synthetic_non_power_of_two(proj):
    g = make()
    frames, u, v = render(g, proj=proj, cam=(200, 160), seed=3)
    c = g.decode(frames, proj)
    m, ec, er = errors(c, u, v)
    assert m.mean() > 0.8
    assert np.mean(np.abs(ec) < 0.5) > 0.99 and np.mean(np.abs(er) < 0.5) > 0.99
    assert rms(ec) < 0.1 and rms(er) < 0.1


def test_synthetic_inverse_false():
    g = make(inverse=False)
    frames, u, v = render(g, cam=(200, 160), seed=4)
    c = g.decode(frames, PROJ)
    m, ec, er = errors(c, u, v)
    assert m.mean() > 0.8
    assert rms(ec) < 0.15 and rms(er) < 0.15


@pytest.mark.parametrize("drop", [1, 2])
def test_synthetic_drop_low_bits(drop):
    g = make(drop_low_bits=drop)
    frames, u, v = render(g, cam=(200, 160), seed=5)
    ci = make(drop_low_bits=drop, subpixel=False).decode(frames, PROJ)
    m, eci, eri = errors(ci, u, v)
    block = 1 << drop
    # integer: the block containing the truth (block centre within half a block + rounding)
    assert np.mean(np.abs(eci) <= block / 2 + 0.5) > 0.99
    c = g.decode(frames, PROJ)
    m, ec, er = errors(c, u, v)
    assert rms(ec) < 0.15 and rms(er) < 0.15 and rms(ec) < 0.3 * rms(eci)


def test_coarse_camera():
    """Camera pixels larger than projector pixels (1.6 projector px per camera px): adjacent
    pixels skip codes; decoding stays exact, refinement uses two-step anchors."""
    g = make()
    frames, u, v = render(g, cam=(200, 160), scale=1.6, ss=6, blur=0.5, seed=6)
    c = g.decode(frames, PROJ)
    m, ec, er = errors(c, u, v)
    assert m.mean() > 0.5
    assert np.mean(np.abs(ec) < 1.0) > 0.99 and np.mean(np.abs(er) < 1.0) > 0.99


def _timing_frames(shape=(1024, 1280), **kw):
    g = make(**kw)
    h, w = shape
    frames = []
    rng = np.random.default_rng(0)
    noise = rng.normal(0, 40, shape).astype(np.float32)
    for p in g.patterns(PROJ):
        f = cv2.resize(p.image, (w, h), interpolation=cv2.INTER_LINEAR).astype(np.float32)
        frames.append(np.clip(f * 3000 / 255 + 200 + noise, 0, 65535).astype(np.uint16))
    return g, frames


def time_decode(repeats: int = 3, **kw) -> float:
    g, frames = _timing_frames(**kw)
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        g.decode(frames, PROJ)
        best = min(best, time.perf_counter() - t)
    return best


def test_timing_1280x1024_uint16(capsys):
    t = time_decode(repeats=1)
    with capsys.disabled():
        print(f"\n[graycode] decode 42 x 1280x1024 uint16: {t * 1000:.0f} ms")



def _turned(xs: np.ndarray, ys: np.ndarray):
    """The synthetic camera turned 45°: stripes of both axes run diagonally in the image."""
    c = np.cos(np.deg2rad(45.0))
    return camera_mapping(c * (xs + ys) - 30.0, c * (ys - xs) + 160.0)


@pytest.mark.parametrize("turn", ["transposed", "diagonal"])
def test_refinement_independent_of_stripe_orientation(scene, turn):
    """Columns and rows refine as well when the stripes lie across the image (a projector
    turned 90°, above the camera, or at 45°) as in the usual layout."""
    g, frames, u, v, _, _ = scene
    base = g.decode(frames, PROJ)
    if turn == "transposed":  # the same frames seen through a camera turned 90°
        frames_t = [np.ascontiguousarray(f.T) for f in frames]
        u_t, v_t = u.T, v.T
    else:
        frames_t, u_t, v_t = render(g, ss=8, cam=(320, 320), mapping=_turned)
    c = g.decode(frames_t, PROJ)
    m, ec, er = errors(c, u_t, v_t)
    _, ec0, er0 = errors(base, u, v)
    for what in ("refined_column", "refined_row"):
        assert c.stats[what] > 0.95 * c.stats["decoded"]
    assert rms(ec) < max(0.1, 1.3 * rms(ec0)) and rms(er) < max(0.1, 1.3 * rms(er0))


def test_reason_map_matches_the_counts(scene):
    g, frames, *_ = scene
    for coding in (g, make(classification="contrast")):
        c = coding.decode(frames, PROJ)
        assert c.reason.shape == c.valid.shape and c.reason_names[0] == "decoded"
        assert np.array_equal(c.reason == 0, c.valid)
        counts = np.bincount(c.reason.ravel(), minlength=len(c.reason_names))
        for code, name in enumerate(c.reason_names):
            assert counts[code] == c.stats[name], name


if __name__ == "__main__":
    g = make()
    for label, kw, rkw in [("default 0.7 proj px/cam px", {}, {}),
                           ("noise 3", {}, {"noise": 3.0}),
                           ("blur 1.5", {}, {"blur": 1.5}),
                           ("inverse=false", {"inverse": False}, {}),
                           ("drop_low_bits=1", {"drop_low_bits": 1}, {}),
                           ("drop_low_bits=2", {"drop_low_bits": 2}, {})]:
        frames, u, v = render(make(**kw), ss=8, **rkw)
        c = make(**kw).decode(frames, PROJ)
        ci = make(subpixel=False, **kw).decode(frames, PROJ)
        m, ec, er = errors(c, u, v)
        mi, eci, eri = errors(ci, u, v)
        exact = np.mean(ci.column[mi] == np.floor(u[mi] + 0.5))
        print(f"{label:28s} valid {m.mean():.3f} int==round(truth) {exact:.3f}"
              f"  col RMS int {rms(eci):.3f} sub {rms(ec):.3f}"
              f"  row RMS int {rms(eri):.3f} sub {rms(er):.3f}  stats {c.stats}")
    for kw in [{}, {"subpixel": False}, {"axes": "columns"}]:
        print(f"decode 42x1280x1024 uint16 {kw}: {time_decode(**kw) * 1000:.0f} ms")
