"""Compiled per-pixel loops of the binary codings' decoder (numba; split by rows across cores).

The decoder of :mod:`dotshell_codings.graycode` makes one pass over a view
(:func:`decode_rows`), in bands of rows taken by the cores one at a time, with no image-sized
temporary per bit. Row by row it:

* classifies (:func:`_classify_row`): reads every frame's row once and decides each projected
  bit of each pixel (the contrast rule or Xu & Aliaga's robust rule after the direct/global
  separation), packing the bits into one word per axis (``value``) and one for the undecided
  ones (``weak``), most significant bit first — the arithmetic is the decoder's documented rule
  in float32 exactly as numpy evaluated it before (NEP 50: Python scalars cast to float32);
  the words live in a three-row ring;
* assembles the coarse code one row behind (:func:`_assemble_row`: gray → binary, the
  one-weak-bit edge tolerance with its 4-neighbour check, out-of-range test) with a flag byte
  per pixel, which :func:`_verdict_row` combines into each pixel's reason and the counts;
  under the adaptive classification :func:`_rescue_row` then gives the row's undecided
  pixels their second chance (the noise-model test, the sign code and the one-step test of
  the weakest bit, reading only them);
* refines to sub-pixel while the row's frames are still in the cache: along the row
  (:func:`_refine_row`) or, one row behind, a step of the scans down the columns
  (:func:`_column_step`). Each scan finds the stripe edges (anchors) between adjacent valid
  pixels as it reaches them, reading the pattern/inverse frames only there, and places the
  pixels since the previous anchor linearly between the two, in place in the coordinate map.
  The column scans cross the bands' borders: the bands are joined in order (:func:`_join`),
  each as soon as the bands up to it are done, as one scan down the whole column would have
  gone.

Two passes over the whole view remain, written with the same row functions:
:func:`classify` for the codings whose projected bits are not Gray bits (their words are
converted, then given to :func:`decode_rows`), and :func:`refine_rows` /
:func:`refine_columns` for the rare view whose stripes lie the other way across the image
than their projector axis suggests, and for a second refinement across the first.

The row functions are compiled on their own and called per row; inlined into the one-pass
kernel they made it take ~100 s of CPU to compile.

Why numba (docs/performance.md, "Decode and triangulation"): numpy needs a full-size
temporary per operation and per bit (the decoder made ~40 passes over 1.3 M-pixel arrays per
bit pair), OpenCV has no kernel for the robust rule or the edge-anchored interpolation, and
threads running numpy release the GIL only inside each small operation. Compiled loops touch each frame pixel once,
keep the per-pixel state in registers; each takes a range of rows (``start``, ``stop``) and
releases the GIL, and :func:`dotshell.runtime.parallel.split` runs the ranges on the cores
(``cache=True`` keeps the compiled code in ``__pycache__``).
"""

from __future__ import annotations

import numba
import numpy as np

from dotshell.runtime import numba_cache

numba_cache.install()  # cache files safe for processes compiling at once

_OPTS = dict(nogil=True, cache=True, error_model="numpy")

#: helpers called per pixel are inlined: a compiled call passing arrays pays reference counting
_INNER = dict(nogil=True, cache=True, error_model="numpy", inline="always")

#: a pass's work on one row (called per row, compiled once for every kernel that calls it)
_ROW = dict(nogil=True, cache=True, error_model="numpy")

#: classification rules of :func:`classify`
CONTRAST, ROBUST = 0, 1


@numba.njit(**_OPTS)
def classify(stack: np.ndarray, inverse: bool, mode: int, axis_bits: np.ndarray,
             sep: np.ndarray, high: np.ndarray, shadow_thr: np.float32, m: np.float32,
             min_contrast: np.float32, contrast_scale: np.float32, one_minus_b: np.float32,
             lg_scale: np.float32, b_level: np.float32, value: np.ndarray, weak: np.ndarray,
             rng: np.ndarray, shadow: np.ndarray, no_direct: np.ndarray, start: int,
             stop: int) -> None:
    """Decide every projected bit of every pixel.

    Args:
        stack: (F, H, W) frames (white, black, then the pairs), uint8/uint16/float32.
        inverse: frames come in pattern/inverse pairs (else pattern vs (white + black) / 2).
        mode: :data:`CONTRAST` or :data:`ROBUST`.
        axis_bits: (A,) int64 bits per axis (pairs are numbered across the axes).
        sep: (P,) bool, pairs used by the direct/global separation (robust).
        high: (P,) bool, pairs decided by the high-frequency branch (robust).
        shadow_thr: float32, white − black below it is shadow.
        m: float32, least direct light (robust).
        min_contrast: float32 (robust high-frequency contrast test).
        contrast_scale: float32, min_contrast (× 0.5 without inverses) for the contrast rule.
        one_minus_b, lg_scale, b_level: float32 constants of the separation.
        value, weak: (A, H, W) uint32 outputs, bit ``nb - 1 - i`` = projected bit i.
        rng: (H, W) float32 output, white − black.
        shadow, no_direct: (H, W) bool outputs.
        start, stop: the rows to do.
    """
    spans = np.empty(rng.shape[1] + 2, np.int64)
    for y in range(start, stop):
        _classify_row(stack, y, inverse, mode, axis_bits, sep, high, shadow_thr, m, min_contrast,
                      contrast_scale, one_minus_b, lg_scale, b_level, value, weak, y, rng[y],
                      shadow[y], no_direct[y], spans)


@numba.njit(**_ROW)
def _classify_row(stack, y, inverse, mode, axis_bits, sep, high, shadow_thr, m, min_contrast,
                  contrast_scale, one_minus_b, lg_scale, b_level, value, weak, vy, r, sh, nd,
                  spans):
    """Row ``y`` of :func:`classify`: the words into ``value``/``weak`` (A, R, W) at row
    ``vy``, white − black, shadow and no-direct into the rows ``r``, ``sh``, ``nd`` (W,)."""
    n_axes = axis_bits.shape[0]
    per_bit = 2 if inverse else 1
    W = r.shape[0]
    zero = np.float32(0.0)
    half = np.float32(0.5)
    black = np.empty(W, np.float32)
    _levels(stack[0, y], stack[1, y], shadow_thr, black, r, sh)
    n_spans = _needed(stack, y, shadow_thr, sh, spans)
    ld = np.empty(W, np.float32)
    lg = np.empty(W, np.float32)
    thr = np.empty(W, np.float32)
    nd[:] = False
    for a in range(n_axes):
        value[a, vy, :] = 0
        weak[a, vy, :] = 0
    for sp in range(n_spans):
        x0, x1 = spans[2 * sp], spans[2 * sp + 1]
        if mode == ROBUST:
            lmax = np.full(x1 - x0, -np.inf, np.float32)
            lmin = np.full(x1 - x0, np.inf, np.float32)
            for k in range(sep.shape[0]):
                if sep[k]:
                    for j in range(2):
                        _extremes(stack[2 + per_bit * k + j, y, x0:x1], black[x0:x1],
                                  lmax, lmin)
            for x in range(x0, x1):
                d = (lmax[x - x0] - lmin[x - x0]) / one_minus_b
                g = lg_scale * (lmin[x - x0] - b_level * lmax[x - x0])
                if g < 0:
                    d = lmax[x - x0]
                    g = zero
                ld[x] = d
                lg[x] = g
                nd[x] = d < m
                thr[x] = min_contrast * d
        else:
            for x in range(x0, x1):
                thr[x] = contrast_scale * max(r[x], zero)
                lg[x] = black[x] + half * r[x]  # the mid level, for frames without inverses
        k = 0
        for a in range(n_axes):
            nb = axis_bits[a]
            val = value[a, vy, x0:x1]
            wk = weak[a, vy, x0:x1]
            i = 0
            while i < nb:
                shift = np.uint32(nb - 1 - i)
                p = stack[2 + per_bit * k, y, x0:x1]
                q = stack[3 + per_bit * k, y, x0:x1] if inverse else stack[1, y, x0:x1]
                b_, t_, n_ = black[x0:x1], thr[x0:x1], nd[x0:x1]
                if mode == ROBUST and i + 1 < nb and not high[k] and not high[k + 1]:
                    # two bits a pass: the words and the levels read once for both
                    _robust_two(p, q, stack[2 + per_bit * (k + 1), y, x0:x1],
                                stack[3 + per_bit * (k + 1), y, x0:x1], b_, ld[x0:x1],
                                lg[x0:x1], m, shift, val, wk)
                    i += 2
                    k += 2
                    continue
                if mode == ROBUST and high[k]:
                    _high_frequency(p, q, b_, t_, n_, shift, val, wk)
                elif mode == ROBUST:
                    _robust(p, q, b_, ld[x0:x1], lg[x0:x1], m, shift, val, wk)
                elif inverse:
                    _contrast(p, q, t_, shift, val, wk)
                else:
                    _contrast_mid(p, lg[x0:x1], t_, shift, val, wk)
                i += 1
                k += 1


@numba.njit(**_INNER)
def _lit_row(stack, y, shadow_thr, lit):
    """``lit`` (W,) = row ``y`` is not shadow (white − black, float32, NaN as 0, reaches
    ``shadow_thr``), as :func:`_levels` decides it."""
    zero = np.float32(0.0)
    for x in range(lit.shape[0]):
        r = np.float32(stack[0, y, x]) - np.float32(stack[1, y, x])
        r = r if np.isfinite(r) else zero
        lit[x] = not r < shadow_thr


@numba.njit(**_INNER)
def _needed(stack, y, shadow_thr, shadow, spans):
    """Runs [x0, x1) of row ``y`` whose bits matter, as pairs in ``spans``; returns how many.
    A shadow pixel's bits matter only to a lit 4-neighbour (its edge-tolerance check): shadow
    pixels with shadow all around are never decoded, and their bits are left 0. The rows
    above and below are tested whole and the neighbourhood in a loop without branches (the
    compiler vectorizes both; pixel by pixel this took ~2.4 ms a view), then the runs are
    read off."""
    H, W = stack.shape[1], stack.shape[2]
    lit = np.empty((3, W), np.bool_)  # above, below, needed
    above, below, need = lit[0], lit[1], lit[2]
    if y > 0:
        _lit_row(stack, y - 1, shadow_thr, above)
    else:
        above[:] = False
    if y + 1 < H:
        _lit_row(stack, y + 1, shadow_thr, below)
    else:
        below[:] = False
    for x in range(1, W - 1):
        need[x] = (not shadow[x]) | (not shadow[x - 1]) | (not shadow[x + 1]) | above[x] | below[x]
    need[0] = not shadow[0] or (W > 1 and not shadow[1]) or above[0] or below[0]
    if W > 1:
        need[W - 1] = not shadow[W - 1] or not shadow[W - 2] or above[W - 1] or below[W - 1]
    n = 0
    inside = False
    for x in range(W):
        if need[x] and not inside:
            spans[2 * n] = x
            inside = True
        elif not need[x] and inside:
            spans[2 * n + 1] = x
            n += 1
            inside = False
    if inside:
        spans[2 * n + 1] = W
        n += 1
    return n


@numba.njit(**_INNER)
def _levels(white, black_in, shadow_thr, black, rng, shadow):
    zero = np.float32(0.0)
    for x in range(white.shape[0]):
        bv = np.float32(black_in[x])
        r = np.float32(white[x]) - bv
        if not np.isfinite(r):
            r = zero
        rng[x] = r
        black[x] = bv
        shadow[x] = r < shadow_thr


@numba.njit(**_INNER)
def _extremes(frame, black, lmax, lmin):
    for x in range(frame.shape[0]):
        v = np.float32(frame[x]) - black[x]
        lmax[x] = max(lmax[x], v)
        lmin[x] = min(lmin[x], v)


@numba.njit(**_INNER)
def _high_frequency(p, q, black, thr, nd, shift, val, wk):
    """Robust rule, high-frequency pair: bit = p > q, uncertain without enough direct light
    or where |p − q| < min_contrast · L_d."""
    for x in range(p.shape[0]):
        d = (np.float32(p[x]) - black[x]) - (np.float32(q[x]) - black[x])
        val[x] |= np.uint32(d > 0) << shift
        wk[x] |= np.uint32(nd[x] | (abs(d) < thr[x])) << shift


@numba.njit(**_INNER)
def _robust(p, q, black, ld, lg, m, shift, val, wk):
    """Xu & Aliaga's rule (see ``robust.robust_bits``), without branches."""
    for x in range(p.shape[0]):
        one, is_zero = _robust_bit(np.float32(p[x]) - black[x], np.float32(q[x]) - black[x],
                                   ld[x], lg[x], m)
        val[x] |= np.uint32(one) << shift
        wk[x] |= np.uint32(~(one | is_zero)) << shift


@numba.njit(**_INNER)
def _robust_two(p, q, p2, q2, black, ld, lg, m, shift, val, wk):
    """:func:`_robust` for two successive pairs (bits ``shift`` and ``shift − 1``) in one loop:
    the words read and written, the levels read, once for both (the classification 18 → 15 ms
    of CPU a view)."""
    next_bit = shift - np.uint32(1)
    for x in range(p.shape[0]):
        b, d, g = black[x], ld[x], lg[x]
        one, is_zero = _robust_bit(np.float32(p[x]) - b, np.float32(q[x]) - b, d, g, m)
        one2, is_zero2 = _robust_bit(np.float32(p2[x]) - b, np.float32(q2[x]) - b, d, g, m)
        val[x] |= (np.uint32(one) << shift) | (np.uint32(one2) << next_bit)
        wk[x] |= (np.uint32(~(one | is_zero)) << shift) | (
            np.uint32(~(one2 | is_zero2)) << next_bit)


@numba.njit(**_INNER)
def _robust_bit(pv, qv, d, g, m):
    """(1, 0) of one bit by the robust rule from pattern and inverse less black (``pv``,
    ``qv``), the direct and global light L_d, L_g and the least usable direct light ``m``; a
    bit that is neither is undecided."""
    enough = d >= m
    wins = enough & (d > g)
    is_zero = (wins & (pv <= qv)) | (~wins & enough & (pv <= d) & (qv >= g))
    one = ((wins & (pv > qv)) | (~wins & enough & (pv >= g) & (qv <= d))) & ~is_zero
    return one, is_zero


@numba.njit(**_INNER)
def _contrast(p, q, thr, shift, val, wk):
    """bit = pattern > inverse, weak where |pattern − inverse| < threshold."""
    for x in range(p.shape[0]):
        d = np.float32(p[x]) - np.float32(q[x])
        val[x] |= np.uint32(d > 0) << shift
        wk[x] |= np.uint32(abs(d) < thr[x]) << shift


@numba.njit(**_INNER)
def _contrast_mid(p, mid, thr, shift, val, wk):
    """Without inverses: bit = pattern > (white + black) / 2."""
    for x in range(p.shape[0]):
        d = np.float32(p[x]) - mid[x]
        val[x] |= np.uint32(d > 0) << shift
        wk[x] |= np.uint32(abs(d) < thr[x]) << shift


@numba.njit(**_INNER)
def _sure(v, w, bit):
    """0 or 1 where the word pair (``v`` value, ``w`` weak) has ``bit`` decided, else -1."""
    if w & bit:
        return -1
    return 1 if v & bit else 0


@numba.njit(**_INNER)
def _on_edge(a, b, c, d):
    """A 4-neighbour has the bit surely 1 and one has it surely 0 (:func:`_sure` of the
    neighbours above, below, left and right; −1 for none)."""
    return max(a, b, c, d) == 1 and (a == 0 or b == 0 or c == 0 or d == 0)


#: bits of the per-pixel flags of :func:`_assemble_row`
BAD, TOLERATED, OUT_OF_RANGE = 1, 2, 4


@numba.njit(**_INNER)
def _centre(c, block, offset, size):
    """Projector coordinate (float32) of the centre of coarse code ``c``'s block, clipped."""
    lo = np.int64(c) * block - offset
    hi = lo + (block - 1)
    return np.float32(0.5 * (max(lo, 0) + min(hi, size - 1)))


@numba.njit(**_ROW)
def _assemble_row(value, weak, up, here, down, shadow, nb, block, offset, size, code, integer,
                  flags):
    """Coarse code of one axis, one row, from its packed Gray words: row ``here`` of
    ``value``/``weak`` (R, W) (``up``/``down``: the rows above and below, −1 at the image
    border) into the rows ``code`` int32, ``integer`` float32 (projector coordinate of the
    block centre, clipped) and ``flags`` uint8 (W,): :data:`BAD` (weak and not tolerated),
    :data:`TOLERATED`, :data:`OUT_OF_RANGE` (block off the projector); all 0 in ``shadow``
    (never decoded). Gray → binary by prefix XOR. A single weak bit is harmless when flipping
    it moves the code by one step and the pixel is on that bit's stripe edge (a 4-neighbour
    where the bit is surely 1 and one where it is surely 0); more weak bits, or one off its
    edge, make the pixel bad."""
    top = size - 1
    for x in range(value.shape[1]):
        if shadow[x]:
            code[x] = 0
            integer[x] = 0
            flags[x] = 0
            continue
        b = np.int64(value[here, x])
        b ^= b >> 1
        b ^= b >> 2
        b ^= b >> 4
        b ^= b >> 8
        b ^= b >> 16
        c = np.int32(b)
        code[x] = c
        wk = weak[here, x]
        f = 0
        if wk != 0:
            f = BAD
            if (wk & (wk - np.uint32(1))) == 0:  # exactly one weak bit
                mask = np.int32(wk) * 2 - 1  # flipping that Gray bit: binary bits k..0
                flipped = c ^ mask
                # the neighbours read here, not in a function given the arrays: an inlined
                # call taking arrays counted references on them per pixel (~5 % of the CPU)
                if abs(flipped - c) == 1 and _on_edge(
                        _sure(value[up, x], weak[up, x], wk) if up >= 0 else -1,
                        _sure(value[down, x], weak[down, x], wk) if down >= 0 else -1,
                        _sure(value[here, x - 1], weak[here, x - 1], wk) if x > 0 else -1,
                        _sure(value[here, x + 1], weak[here, x + 1], wk)
                        if x + 1 < value.shape[1] else -1):
                    f = TOLERATED
        lo = np.int64(c) * block - offset
        if lo + (block - 1) < 0 or lo > top:
            f |= OUT_OF_RANGE
        flags[x] = f
        integer[x] = _centre(c, block, offset, size)


@numba.njit(**_OPTS)
def block_centres(code: np.ndarray, valid: np.ndarray, block: int, offset: int, size: int,
                  coord: np.ndarray, start: int, stop: int) -> None:
    """``coord`` (H, W) float32 = the block centre of ``code`` at the valid pixels (the coarse
    coordinates :func:`_assemble_row` gave them), rows ``start`` to ``stop``."""
    for y in range(start, stop):
        for x in range(code.shape[1]):
            if valid[y, x]:
                coord[y, x] = _centre(code[y, x], block, offset, size)


@numba.njit(**_ROW)
def _verdict_row(shadow, no_direct, flags, fy, valid, reason, counts):
    """Each pixel's fate in one row from the axes' flags (A, R, W) at row ``fy``
    (:func:`_assemble_row`): ``reason`` 0 decoded (``valid``), 1 shadow, 2 a bit undecided
    (weak and not tolerated on any axis, or no direct light), 3 off the projector, the first
    that holds; ``counts`` (6,): the pixels of each reason, (4) the decoded pixels with a
    tolerated bit and (5) those :func:`_rescue_row` decodes (0 here). The other arguments are
    rows (W,). The axes' flags are combined into ``flags[0, fy]``."""
    n_axes = flags.shape[0]
    W = shadow.shape[0]
    f = flags[0, fy]
    for a in range(1, n_axes):  # the axes' flags combined into the first's row
        other = flags[a, fy]
        for x in range(W):
            f[x] |= other[x]
    # without branches, each reason counted in a sum of its own: the compiler vectorizes it
    n_shadow = n_bad = n_off = n_tolerated = 0
    for x in range(W):
        sh = shadow[x]
        bad = ((f[x] & BAD) != 0) | no_direct[x]
        off = (f[x] & OUT_OF_RANGE) != 0
        r = 1 if sh else 2 if bad else 3 if off else 0
        reason[x] = r
        valid[x] = r == 0
        n_shadow += sh
        n_bad += bad & (not sh)
        n_off += off & (not sh) & (not bad)
        n_tolerated += (r == 0) & ((f[x] & TOLERATED) != 0)
    counts[0] = W - n_shadow - n_bad - n_off
    counts[1] = n_shadow
    counts[2] = n_bad
    counts[3] = n_off
    counts[4] = n_tolerated
    counts[5] = 0


#: entries of :func:`decode_rows`' ``rescue`` (float32): the noise model's 2 × floor and gain
#: (``var(p − q) = 2 floor + gain (p + q − 2 black)``, frame units), the sigmas a pixel's
#: bits (all but its weakest) must stand beyond the global-light bound, the edge ratio
#: (:func:`_beside_edge`) and the code steps a neighbour may be away (:func:`_off_its_neighbours`)
FLOOR2, GAIN, SIGMAS, EDGE, STEPS = range(5)


@numba.njit(**_ROW)
def _rescue_row(stack, y, axis_bits, sep, axes, gray_base, rescue, one_minus_b, lg_scale,
                b_level, code, coord, valid, reason, counts):
    """The adaptive classification's second chance for the pixels of row ``y`` that
    :func:`_verdict_row` left with a bit undecided (``reason`` 2): such a pixel is decoded by
    the sign of every pattern − inverse (the contrast rule without its threshold) when all its
    bits but the weakest stand ``rescue[SIGMAS]`` noise sigmas beyond what global light could
    do to them (:func:`_all_but_one_sure`), flipping that weakest bit (if one falls below)
    moves its axis's code by one step, its code is on the projector on every axis, it is
    not beside an edge of the white − black image (:func:`_beside_edge`) and its code is
    continuous with its neighbours' (:func:`_off_its_neighbours`). The
    one-step test is the edge tolerance robust gives a single weak bit (:func:`_assemble_row`):
    a weak bit of the finest stripes' edge costs at most one code step, a weak coarse bit
    would throw the pixel blocks away (on the clean metal cylinder at full resolution such
    pixels on the silhouette's outer ring were 14 of the 16 wrong codes the rescue added).
    Robust's other half of that tolerance, a 4-neighbour with the bit surely 1 and one with
    it surely 0 in robust's words, is not asked: the pixels robust leaves uncertain lie in
    runs, and with it the rescue kept 2 of those 1 062 pixels (docs/codings.md). Only those
    pixels are read again (their frames are still in the cache), so the cost follows the
    pixels robust leaves uncertain; :func:`decode_rows` calls it only for rows that have
    some. ``gray_base`` (A,) int64: the projected bit (MSB-first
    index) that the other projected bits are XORed with, −1 where the projected bits are the
    Gray bits (the XOR codings' base bit flips every Gray bit: never one step); ``code``,
    ``coord`` (A, H, W); ``valid``, ``reason``, ``counts``: row ``y``'s (as
    :func:`_verdict_row`'s)."""
    n_axes = axis_bits.shape[0]
    codes = np.empty(n_axes, np.int32)
    # the row's pixels to test listed first, in a loop of their own: a loop over the whole
    # row around the tests' code cost ~3.6 ns a pixel even where it skipped them (4.3 ms of
    # CPU a full view, with no pixel to test; now ~0.1 ms)
    at = np.empty(reason.shape[0], np.int64)
    n = 0
    for x in range(reason.shape[0]):
        at[n] = x
        n += reason[x] == 2
    for i in range(n):
        x = at[i]
        weakest = _all_but_one_sure(stack, y, x, sep, rescue, one_minus_b, lg_scale, b_level)
        if weakest < 0:
            continue
        inside = True
        k = 0
        for a in range(n_axes):
            nb = axis_bits[a]
            codes[a] = _sign_code(stack, y, x, k, nb, gray_base[a], -1)
            if k <= weakest < k + nb and abs(_sign_code(stack, y, x, k, nb, gray_base[a],
                                                         weakest - k) - codes[a]) != 1:
                inside = False  # the weakest bit is not a one-step bit: robust's tolerance
            k += nb
            lo = np.int64(codes[a]) * axes[a, BLOCK] - axes[a, OFFSET]
            if lo + (axes[a, BLOCK] - 1) < 0 or lo > axes[a, SIZE] - 1:
                inside = False
        if not inside or _beside_edge(stack, y, x, rescue[EDGE]):
            continue
        if _off_its_neighbours(stack, y, x, axis_bits, gray_base, codes, rescue[STEPS]):
            continue
        for a in range(n_axes):
            code[a, y, x] = codes[a]
            coord[a, y, x] = _centre(codes[a], axes[a, BLOCK], axes[a, OFFSET], axes[a, SIZE])
        reason[x] = 0
        valid[x] = True
        counts[0] += 1
        counts[2] -= 1
        counts[5] += 1


@numba.njit(**_INNER)
def _beside_edge(stack, y, x, ratio):
    """Pixel (y, x) has an 8-neighbour whose white − black is below ``ratio`` × its own (not
    finite counts as 0; neighbours outside the image do not count): it lies on a silhouette, a
    shadow's edge or a depth edge, where its footprint mixes surfaces or spans several
    projector columns, so a bit taken by its sign can cost more than the one code step the
    rescue allows (the adaptive classification's last test; ``ratio`` 0: never)."""
    if not ratio > 0:
        return False
    here = np.float32(stack[0, y, x]) - np.float32(stack[1, y, x])
    floor = ratio * here
    for ny in range(max(y - 1, 0), min(y + 2, stack.shape[1])):
        for nx in range(max(x - 1, 0), min(x + 2, stack.shape[2])):
            r = np.float32(stack[0, ny, nx]) - np.float32(stack[1, ny, nx])
            if not np.isfinite(r):
                r = np.float32(0.0)
            if r < floor:
                return True
    return False


@numba.njit(**_INNER)
def _off_its_neighbours(stack, y, x, axis_bits, gray_base, codes, steps):
    """One of pixel (y, x)'s 8 neighbours (inside the image) has, on some axis, a sign code
    (:func:`_sign_code`) more than ``steps`` code steps from the pixel's own ``codes`` (A,)
    (the adaptive classification's continuity test; ``steps`` 0: never). The rescue's
    one-step tolerance holds where a camera pixel sees about one code step; where its
    neighbours' codes lie further apart the pixel sees a surface edge-on (it spans several
    projector columns: on the mouse phantom at full resolution the rescued codes 1.5-2.8
    projector px off lay there, the surface at 85-88° to the view, its neighbours' codes
    10-50 steps apart) or straddles a depth edge or silhouette (its neighbours see another
    surface), and a bit taken by its sign can cost more than one step."""
    if not steps > 0:
        return False
    k = 0
    for a in range(axis_bits.shape[0]):
        nb = axis_bits[a]
        for ny in range(max(y - 1, 0), min(y + 2, stack.shape[1])):
            for nx in range(max(x - 1, 0), min(x + 2, stack.shape[2])):
                if (ny != y or nx != x) and abs(np.float32(
                        _sign_code(stack, ny, nx, k, nb, gray_base[a], -1) - codes[a])) > steps:
                    return True
        k += nb
    return False


@numba.njit(**_INNER)
def _sign_code(stack, y, x, first, nb, base, flip):
    """Coarse code of pixel (y, x) on the axis whose ``nb`` pairs start at pair ``first``,
    every projected bit by the sign of pattern − inverse, projected bit ``flip`` (MSB-first
    index; −1: none) taken the other way; the projected bits are XORed with bit ``base``
    (MSB-first index) back into Gray bits unless ``base`` is −1."""
    g = np.int64(0)
    for i in range(nb):
        d = np.float32(stack[2 + 2 * (first + i), y, x]) - np.float32(
            stack[3 + 2 * (first + i), y, x])
        g = (g << 1) | np.int64((d > 0) != (i == flip))
    if base >= 0:
        shift = nb - 1 - base
        if (g >> shift) & 1:
            g ^= ((np.int64(1) << nb) - 1) ^ (np.int64(1) << shift)
    g ^= g >> 1
    g ^= g >> 2
    g ^= g >> 4
    g ^= g >> 8
    g ^= g >> 16
    return np.int32(g)


@numba.njit(**_INNER)
def _all_but_one_sure(stack, y, x, sep, rescue, one_minus_b, lg_scale, b_level):
    """The index of pixel (y, x)'s one weak pair when all its bits but that one stand
    ``rescue[SIGMAS]`` noise sigmas beyond undecidable: ``z = (|p − q| − max(L_g − L_d, 0))
    / σ`` below it in at most one pattern/inverse pair (the second smallest z reaches it), with
    ``σ² = max(2 floor + gain · max(p + q − 2 black, 0), 1e-6)`` and
    ``L_d``, ``L_g`` from the pairs ``sep`` as the robust rule separates them. A pattern's and
    its inverse's global light differ by at most ``L_g − L_d``, so beyond it a bit's sign is
    sure. −1 when two pairs fall below, ``sep.shape[0]`` when none does (every bit is sure).
    float32 throughout, as numpy evaluates the documented formula; the finest pairs (the
    weakest, mostly) first, and the second pair below the bound ends the test. Before the
    separation's frames are read, ``|p − q| / σ`` (an upper bound of z: the ambiguous band is
    ≥ 0) ends it where two pairs fall below by that alone (:func:`_two_surely_weak`)."""
    black = np.float32(stack[1, y, x])
    if _two_surely_weak(stack, y, x, sep.shape[0], rescue, black):
        return -1
    lmax = np.float32(-np.inf)
    lmin = np.float32(np.inf)
    for k in range(sep.shape[0]):
        if sep[k]:
            for j in range(2):
                v = np.float32(stack[2 + 2 * k + j, y, x]) - black
                lmax = max(lmax, v)
                lmin = min(lmin, v)
    d = (lmax - lmin) / one_minus_b
    g = lg_scale * (lmin - b_level * lmax)
    if g < 0:
        d = lmax
        g = np.float32(0.0)
    ambiguous = max(g - d, np.float32(0.0))
    zero = np.float32(0.0)
    weakest = sep.shape[0]
    for k in range(sep.shape[0] - 1, -1, -1):
        p = np.float32(stack[2 + 2 * k, y, x])
        q = np.float32(stack[3 + 2 * k, y, x])
        var = max(rescue[FLOOR2] + rescue[GAIN] * max(p + q - np.float32(2) * black, zero),
                  np.float32(1e-6))
        z = (abs(p - q) - ambiguous) / np.sqrt(var)
        if not z >= rescue[SIGMAS]:  # NaN counts as weak
            if weakest < sep.shape[0]:
                return -1
            weakest = k
    return weakest


@numba.njit(**_INNER)
def _two_surely_weak(stack, y, x, n_pairs, rescue, black):
    """Two of pixel (y, x)'s ``n_pairs`` pattern/inverse pairs have ``|p − q| / σ`` below
    ``rescue[SIGMAS]`` (NaN counts as below; σ as :func:`_all_but_one_sure`'s): their z is
    smaller still, so the pixel cannot be rescued, whatever the direct/global separation
    (on the agar body without PDI most uncertain pixels end here, after two pairs)."""
    zero = np.float32(0.0)
    below = 0
    for k in range(n_pairs - 1, -1, -1):
        p = np.float32(stack[2 + 2 * k, y, x])
        q = np.float32(stack[3 + 2 * k, y, x])
        var = max(rescue[FLOOR2] + rescue[GAIN] * max(p + q - np.float32(2) * black, zero),
                  np.float32(1e-6))
        if not abs(p - q) / np.sqrt(var) >= rescue[SIGMAS]:
            below += 1
            if below == 2:
                return True
    return False


@numba.njit(**_ROW)
def _changes_row(code, valid, y, counts):
    """Code changes between valid pixels of row ``y``: along the row (``counts[0]``) and
    down to the next row (``counts[1]``)."""
    H, W = code.shape
    along_rows = 0
    along_cols = 0
    here, valid_here = code[y], valid[y]
    for x in range(W - 1):  # without branches (vectorized)
        along_rows += valid_here[x] & valid_here[x + 1] & (here[x + 1] != here[x])
    if y + 1 < H:
        below, valid_below = code[y + 1], valid[y + 1]
        for x in range(W):
            along_cols += valid_here[x] & valid_below[x] & (below[x] != here[x])
    counts[0] = along_rows
    counts[1] = along_cols


@numba.njit(**_INNER)
def _flip_bit(j, nb):
    """Projected bit (MSB-first index) that flips on entering coarse code ``j``."""
    top = (np.int64(1) << nb) - 1
    if j > top:
        j = top
    if j < 1:
        return nb - 1
    t = 0
    while not (j >> t) & 1:
        t += 1
    return nb - 1 - t


@numba.njit(**_INNER)
def _d(stack, inverse, fp, y, x, rng):
    """Range-normalised difference signal of the pair whose pattern is frame ``fp``."""
    p = np.float32(stack[fp, y, x])
    if inverse:
        q = np.float32(stack[fp + 1, y, x])
    else:
        q = np.float32(stack[1, y, x]) + np.float32(0.5) * rng[y, x]
    return (p - q) / max(rng[y, x], np.float32(1e-6))


@numba.njit(**_OPTS)
def flip_table(nb: int) -> np.ndarray:
    """(2^nb + 2,) int64: the projected bit (MSB-first index) that flips on entering each
    coarse code (:func:`_flip_bit`), looked up per anchor instead of counting its zeros."""
    table = np.empty((1 << nb) + 2, np.int64)
    for j in range(table.shape[0]):
        table[j] = _flip_bit(j, nb)
    return table


@numba.njit(**_INNER)
def _anchor(stack, inverse, rng, code, y0, x0, y1, x1, s, flip, block, offset, first_pair,
            anchor_bit):
    """(position along the scan line, projector coordinate) of the stripe edge between the
    adjacent valid pixels (y0, x0) = sample ``s`` and (y1, x1) = sample ``s + 1``, or NaN,
    NaN (``flip``: :func:`flip_table` of the axis)."""
    nan32 = np.float32(np.nan)
    a, b = code[y0, x0], code[y1, x1]
    k = abs(b - a)
    if k == 0 or k > 2 or (anchor_bit >= 0 and k != 1):
        return nan32, nan32
    base = np.int64(min(a, b))
    if anchor_bit >= 0 and flip[base + 1] != anchor_bit:
        return nan32, nan32
    per_bit = 2 if inverse else 1
    t = np.float32(0.0)
    for step in range(1, k + 1):
        fp = 2 + per_bit * (first_pair + flip[base + step])
        d0 = _d(stack, inverse, fp, y0, x0, rng)
        d1 = _d(stack, inverse, fp, y1, x1, rng)
        den = d0 - d1
        c = d0 / den if den != 0 else np.float32(0.5)
        t += min(max(c, np.float32(0.0)), np.float32(1.0))
    if k > 1:  # the mean of the k crossings; t / 1 is t, without the division's cost
        t = t / np.float32(k)
    pos = np.float32(np.float64(s) + np.float64(t))
    val = np.float32((base + 1) * block - offset - 0.5 + 0.5 * (k - 1) * block)
    return pos, val


@numba.njit(**_INNER)
def _interpolate(i, c, pl, vl, pr, vr, block, offset, max_span):
    """Coordinate of sample ``i`` (code ``c``) between the anchors (pl, vl) and (pr, vr), and
    whether it holds (anchors at most ``max_span`` blocks apart, its own block between)."""
    span = vr - vl
    lo = np.int64(c) * block - offset
    centre = 0.5 * (lo + lo + (block - 1))
    if (span != 0 and abs(span) <= max_span * block and pr > pl
            and centre >= min(vl, vr) and centre <= max(vl, vr)):
        return np.float32(np.float64(vl) + (np.float64(i) - np.float64(pl))
                          / np.float64(pr - pl) * np.float64(span)), True
    return np.float32(np.nan), False


@numba.njit(**_OPTS)
def refine_rows(stack: np.ndarray, inverse: bool, rng: np.ndarray, code: np.ndarray,
                valid: np.ndarray, flip: np.ndarray, block: int, offset: int, first_pair: int,
                anchor_bit: int, max_span: int, first: bool, coord: np.ndarray,
                ok: np.ndarray, start: int, stop: int) -> None:
    """Sub-pixel coordinates along the camera rows ``start`` to ``stop``, in one pass: each
    stripe edge between horizontally adjacent valid pixels (an anchor, :func:`_anchor`) is
    found as the scan reaches it, and the samples since the previous anchor of the same run of
    valid samples are placed linearly between the two (at most ``max_span`` blocks apart,
    each sample's own block between them).

    ``coord`` (H, W) float32 holds the coarse coordinate: refined samples get their sub-pixel
    coordinate, invalid ones NaN, the rest keep theirs. ``ok`` (H, W) bool marks the refined
    samples; ``first``: this is the axis's first pass (``ok`` is cleared), else samples
    already refined (by the other direction's pass) are left as they are."""
    for y in range(start, stop):
        if first:
            for x in range(ok.shape[1]):
                ok[y, x] = False
        _refine_row(stack, inverse, rng, code, valid, flip, block, offset, first_pair,
                    anchor_bit, max_span, coord, ok, y)


@numba.njit(**_ROW)
def _refine_row(stack, inverse, rng, code, valid, flip, block, offset, first_pair, anchor_bit,
                max_span, coord, ok, y):
    """Row ``y`` of :func:`refine_rows` (its ``ok`` row already cleared if ``first``: one
    compiled variant for it and :func:`decode_rows`, whose pass is never the first)."""
    W = code.shape[1]
    nan32 = np.float32(np.nan)
    prev = -1
    prev_pos = np.float32(0.0)
    prev_val = np.float32(0.0)
    bad = -1
    valid_y, code_y, coord_y, ok_y = valid[y], code[y], coord[y], ok[y]
    for x in range(W):
        if not valid_y[x]:
            bad = x
            coord_y[x] = nan32
            continue
        if x + 1 == W or not valid_y[x + 1]:
            continue
        pos, val = _anchor(stack, inverse, rng, code, y, x, y, x + 1, x, flip, block,
                           offset, first_pair, anchor_bit)
        if np.isnan(pos):
            continue
        if prev >= 0 and bad <= prev:
            for i in range(prev + 1, x + 1):
                if not ok_y[i]:
                    f, good = _interpolate(i, code_y[i], prev_pos, prev_val, pos, val,
                                           block, offset, max_span)
                    if good:
                        coord_y[i] = f
                        ok_y[i] = True
        prev, prev_pos, prev_val = x, pos, val


@numba.njit(**_OPTS)
def refine_columns(stack: np.ndarray, inverse: bool, rng: np.ndarray, code: np.ndarray,
                   valid: np.ndarray, flip: np.ndarray, block: int, offset: int,
                   first_pair: int, anchor_bit: int, max_span: int, first: bool,
                   coord: np.ndarray, ok: np.ndarray, start: int, stop: int) -> None:
    """:func:`refine_rows` down the camera columns ``start`` to ``stop``, without transposing:
    the image is scanned row by row, so that every read runs along memory, with each column's
    scan state (previous anchor, last invalid sample: :func:`_column_step`) kept apart."""
    scan_i = np.full((4, stop - start), -1, np.int64)
    scan_f = np.zeros((4, stop - start), np.float32)
    for y in range(code.shape[0]):
        if first:
            for x in range(start, stop):
                ok[y, x] = False
        _column_step(stack, inverse, rng, code, valid, flip, block, offset, first_pair,
                     anchor_bit, max_span, coord, ok, y, start, stop, scan_i, scan_f)


#: rows of a column scan's state (:func:`_column_step`): int64 ``scan_i`` and float32 ``scan_f``
PREV, BAD_ROW, FIRST, BAD_BEFORE_FIRST = 0, 1, 2, 3  # scan_i: rows, −1 for none
PREV_POS, PREV_VAL, FIRST_POS, FIRST_VAL = 0, 1, 2, 3  # scan_f: the anchors' position, value


@numba.njit(**_ROW)
def _column_step(stack, inverse, rng, code, valid, flip, block, offset, first_pair, anchor_bit,
                 max_span, coord, ok, y, start, stop, scan_i, scan_f):
    """Row ``y`` of the scans down the columns ``start`` to ``stop`` (:func:`refine_columns`),
    with each column's state in ``scan_i`` (4, n) int64 / ``scan_f`` (4, n) float32 (rows
    :data:`PREV` …): the previous anchor (row, position, value), the last invalid row, and the
    scan's first anchor with the last invalid row before it (what a scan started mid-image
    leaves for :func:`_join`). ``ok``'s row ``y`` is cleared by :func:`refine_columns` in
    its first pass. (numba compiles a variant for the literal ``start`` = 0 that
    :func:`decode_rows` passes: given as an int64, one variant fewer to compile, the full view's
    CPU was 2-4 % higher.)"""
    H = code.shape[0]
    nan32 = np.float32(np.nan)
    for x in range(start, stop):
        j = x - start
        if not valid[y, x]:
            scan_i[BAD_ROW, j] = y
            coord[y, x] = nan32
            continue
        if y + 1 == H or not valid[y + 1, x]:
            continue
        pos, val = _anchor(stack, inverse, rng, code, y, x, y + 1, x, y, flip, block,
                           offset, first_pair, anchor_bit)
        if np.isnan(pos):
            continue
        p = scan_i[PREV, j]
        if p >= 0:
            if scan_i[BAD_ROW, j] <= p:
                _fill_column(code, coord, ok, x, p, y, scan_f[PREV_POS, j],
                             scan_f[PREV_VAL, j], pos, val, block, offset, max_span)
        elif scan_i[FIRST, j] < 0:
            scan_i[FIRST, j] = y
            scan_i[BAD_BEFORE_FIRST, j] = scan_i[BAD_ROW, j]
            scan_f[FIRST_POS, j] = pos
            scan_f[FIRST_VAL, j] = val
        scan_i[PREV, j] = y
        scan_f[PREV_POS, j] = pos
        scan_f[PREV_VAL, j] = val


@numba.njit(**_INNER)
def _fill_column(code, coord, ok, x, p, y, pl, vl, pr, vr, block, offset, max_span):
    """Samples ``p + 1`` to ``y`` of column ``x`` placed between the anchors at rows ``p``
    (pl, vl) and ``y`` (pr, vr) (:func:`_interpolate`), except those already refined."""
    for i in range(p + 1, y + 1):
        if not ok[i, x]:
            f, good = _interpolate(i, code[i, x], pl, vl, pr, vr, block, offset, max_span)
            if good:
                coord[i, x] = f
                ok[i, x] = True


#: columns of :func:`decode_rows`' per-axis settings (``axes``, (A, 6) int64)
BLOCK, OFFSET, SIZE, FIRST_PAIR, ANCHOR_BIT, MAX_SPAN = range(6)

#: phases of :func:`decode_rows`
BAND, JOIN = 0, 1


@numba.njit(**_OPTS)
def decode_rows(stack: np.ndarray, inverse: bool, mode: int, axis_bits: np.ndarray,
                sep: np.ndarray, high: np.ndarray, shadow_thr: np.float32, m: np.float32,
                min_contrast: np.float32, contrast_scale: np.float32, one_minus_b: np.float32,
                lg_scale: np.float32, b_level: np.float32, axes: np.ndarray, flips: np.ndarray,
                down: np.ndarray, refine: bool, classified: bool, adaptive: bool,
                gray_base: np.ndarray, rescue: np.ndarray, value: np.ndarray,
                weak: np.ndarray, code: np.ndarray, coord: np.ndarray, ok: np.ndarray,
                valid: np.ndarray, reason: np.ndarray, counts: np.ndarray, changed: np.ndarray,
                rng: np.ndarray, shadow: np.ndarray, no_direct: np.ndarray, scan_i: np.ndarray,
                scan_f: np.ndarray, phase: int, band: int, start: int, stop: int) -> None:
    """The decode of a band of rows, ``start`` to ``stop``, in one pass (``phase`` =
    :data:`BAND`): each row is classified (:func:`_classify_row`) one row ahead of its
    assembly (:func:`_assemble_row`, which looks at the rows above and below); its verdict and
    sub-pixel refinement along the row follow at once, while the row's frames are still in
    the cache; the scans down the columns and the code-change counts run one row behind
    (:func:`_behind`). The projected bits live in a three-row ring, not in image-sized words;
    the rows just outside the band are classified again into the ring rather than read from
    the neighbouring band's thread. ``phase`` = :data:`JOIN` joins band ``band`` (first row
    ``start``) to the bands above it, once they are all done (:func:`_join`; the bands
    after it may still be running: a join reads and writes only rows of the bands up to
    its own and band 0's scan state).

    Args (the classification's as :func:`classify`'s, then):
        axes: (A, 6) int64 per axis: block, offset, size, first pair, anchor bit (−1: all),
            max anchor span (columns :data:`BLOCK` …).
        flips: (A, T) int64, each axis's :func:`flip_table` (padded).
        down: (A,) bool, the axis is refined down the columns (else along the rows).
        refine: sub-pixel refinement (else the block centres, NaN where not decoded).
        classified: the Gray words are given in ``value``/``weak`` (A, H, W) with ``rng``,
            ``shadow``, ``no_direct`` (a coding whose projected bits are not Gray bits:
            :func:`classify`, then its own conversion), else they are made here
            (``value``/``weak`` unused).
        adaptive: the pixels left with a bit undecided get :func:`_rescue_row`'s second
            chance (``mode`` is then :data:`ROBUST`), with ``gray_base`` (A,) int64 and
            ``rescue`` (5,) float32 (:data:`FLOOR2` …).
        code, coord, ok: (A, H, W) int32 / float32 / bool outputs: coarse code, projector
            coordinate (sub-pixel where refined, NaN where not decoded), refined.
        valid, reason, counts: (H, W) bool, (H, W) uint8, (H, 6) int64 (:func:`_verdict_row`).
        changed: (A, H, 2) int64 code changes per row (:func:`_changes_row`).
        rng, shadow, no_direct: (H, W) as :func:`classify`'s (outputs unless ``classified``).
        scan_i, scan_f: (B, A, 4, W) the column scans' state per band (:func:`_column_step`).
        phase, band, start, stop: as above. In its pass, a band leaves its last row's column
            steps and change counts to the join (they need the next band's first row), except
            the last band.
    """
    if phase == JOIN:
        _join(stack, inverse, rng, axes, flips, down, refine, code, coord, ok, valid, changed,
              scan_i, scan_f, band, start)
        return
    n_axes = axis_bits.shape[0]
    H, W = rng.shape
    if not classified:
        value = np.zeros((n_axes, 3, W), np.uint32)
        weak = np.zeros((n_axes, 3, W), np.uint32)
    flags = np.empty((n_axes, 1, W), np.uint8)
    halo_r = np.empty(W, np.float32)
    halo_sh = np.empty(W, np.bool_)
    halo_nd = np.empty(W, np.bool_)
    spans = np.empty(W + 2, np.int64)
    nan32 = np.float32(np.nan)
    scan_i[band] = -1
    scan_f[band] = 0
    for n in range(max(start - 1, 0), stop + 1):  # classify row n, then finish row n - 1
        if n < H and not classified:
            inside = start <= n < stop
            _classify_row(stack, n, inverse, mode, axis_bits, sep, high, shadow_thr, m,
                          min_contrast, contrast_scale, one_minus_b, lg_scale, b_level, value,
                          weak, n % 3, rng[n] if inside else halo_r,
                          shadow[n] if inside else halo_sh,
                          no_direct[n] if inside else halo_nd, spans)
        y = n - 1
        if y < start or y >= H:
            continue
        up = -1 if y == 0 else (y - 1) if classified else (y - 1) % 3
        dn = -1 if n == H else n if classified else n % 3
        here = y if classified else y % 3
        for a in range(n_axes):
            _assemble_row(value[a], weak[a], up, here, dn, shadow[y], axis_bits[a],
                          axes[a, BLOCK], axes[a, OFFSET], axes[a, SIZE], code[a, y],
                          coord[a, y], flags[a, 0])
            ok[a, y, :] = False
        _verdict_row(shadow[y], no_direct[y], flags, 0, valid[y], reason[y], counts[y])
        if adaptive and counts[y, 2] > 0:  # a pixel of the row has a bit undecided
            _rescue_row(stack, y, axis_bits, sep, axes, gray_base, rescue, one_minus_b,
                        lg_scale, b_level, code, coord, valid[y], reason[y], counts[y])
        for a in range(n_axes):
            if not refine:
                for x in range(W):
                    if not valid[y, x]:
                        coord[a, y, x] = nan32
            elif not down[a]:
                _refine_row(stack, inverse, rng, code[a], valid, flips[a], axes[a, BLOCK],
                            axes[a, OFFSET], axes[a, FIRST_PAIR], axes[a, ANCHOR_BIT],
                            axes[a, MAX_SPAN], coord[a], ok[a], y)
        if y > start:
            _behind(stack, inverse, rng, axes, flips, down, refine, code, coord, ok, valid,
                    changed, scan_i[band], scan_f[band], y - 1)
    if stop == H:
        _behind(stack, inverse, rng, axes, flips, down, refine, code, coord, ok, valid, changed,
                scan_i[band], scan_f[band], H - 1)


@numba.njit(**_ROW)
def _behind(stack, inverse, rng, axes, flips, down, refine, code, coord, ok, valid, changed,
            scan_i, scan_f, y):
    """What :func:`decode_rows` does one row behind: row ``y``'s code-change counts and
    (``refine``) its step of the column scans (state ``scan_i``/``scan_f`` (A, 4, W))."""
    for a in range(code.shape[0]):
        _changes_row(code[a], valid, y, changed[a, y])
        if refine and down[a]:
            _column_step(stack, inverse, rng, code[a], valid, flips[a], axes[a, BLOCK],
                         axes[a, OFFSET], axes[a, FIRST_PAIR], axes[a, ANCHOR_BIT],
                         axes[a, MAX_SPAN], coord[a], ok[a], y, 0, code.shape[2],
                         scan_i[a], scan_f[a])


@numba.njit(**_ROW)
def _join(stack, inverse, rng, axes, flips, down, refine, code, coord, ok, valid, changed,
          scan_i, scan_f, band, start):
    """Join band ``band`` (first row ``start``) of :func:`decode_rows` to the bands above it,
    in order, once their passes and its own are done: the band above gets its last row's
    column steps and change counts; the samples between each column scan's last anchor above
    and its first anchor in this band are placed, as one scan down the whole column would
    have; the scan goes on with this band's state. Band 0's ``scan_i``/``scan_f`` carry the
    state."""
    _behind(stack, inverse, rng, axes, flips, down, refine, code, coord, ok, valid, changed,
            scan_i[0], scan_f[0], start - 1)
    for a in range(code.shape[0]):
        if not (refine and down[a]):
            continue
        si, sf, bi, bf = scan_i[0, a], scan_f[0, a], scan_i[band, a], scan_f[band, a]
        for x in range(code.shape[2]):
            if bi[FIRST, x] >= 0:
                p = si[PREV, x]
                bad = bi[BAD_BEFORE_FIRST, x] if bi[BAD_BEFORE_FIRST, x] >= 0 else si[BAD_ROW, x]
                if p >= 0 and bad <= p:
                    _fill_column(code[a], coord[a], ok[a], x, p, bi[FIRST, x], sf[PREV_POS, x],
                                 sf[PREV_VAL, x], bf[FIRST_POS, x], bf[FIRST_VAL, x],
                                 axes[a, BLOCK], axes[a, OFFSET], axes[a, MAX_SPAN])
                si[PREV, x] = bi[PREV, x]
                sf[PREV_POS, x] = bf[PREV_POS, x]
                sf[PREV_VAL, x] = bf[PREV_VAL, x]
            si[BAD_ROW, x] = max(si[BAD_ROW, x], bi[BAD_ROW, x])


@numba.njit(**_OPTS)
def difference_extremes(image: np.ndarray, out: np.ndarray, band: int, start: int,
                        stop: int) -> None:
    """``out[band]`` = the least and greatest difference of horizontally adjacent pixels of an
    integer image in rows ``start`` to ``stop`` (0 included: a histogram's range)."""
    low = np.int64(0)
    high = np.int64(0)
    for y in range(start, stop):
        for x in range(image.shape[1] - 1):
            d = np.int64(image[y, x + 1]) - np.int64(image[y, x])
            low = min(low, d)
            high = max(high, d)
    out[band, 0] = low
    out[band, 1] = high


@numba.njit(**_OPTS)
def difference_counts(image: np.ndarray, low: int, counts: np.ndarray, band: int, start: int,
                      stop: int) -> None:
    """``counts[band, i]`` = how often the difference ``low + i`` of horizontally adjacent
    pixels occurs in rows ``start`` to ``stop`` of an integer image."""
    out = counts[band]
    for y in range(start, stop):
        for x in range(image.shape[1] - 1):
            out[np.int64(image[y, x + 1]) - np.int64(image[y, x]) - low] += 1


@numba.njit(**_OPTS)
def model_levels(stack: np.ndarray, least: np.float32, most: np.float32, levels: np.ndarray,
                 band: int, start: int, stop: int) -> None:
    """The noise model's pixels (every second each way; ``w − b > least`` and ``w < most``,
    float32 as numpy compares them) of the sampled rows ``start`` to ``stop`` (image rows
    ``2 start`` …) counted by their level ``w − b`` into ``levels[band]`` (an integer
    stack's levels are integers)."""
    out = levels[band]
    for sy in range(start, stop):
        y = 2 * sy
        for x in range(0, stack.shape[2], 2):
            w = np.float32(stack[0, y, x])
            r = w - np.float32(stack[1, y, x])
            if r > least and w < most:
                out[np.int64(r)] += 1


@numba.njit(**_OPTS)
def model_residuals(stack: np.ndarray, least: np.float32, most: np.float32,
                    first_rank: np.ndarray, ends: np.ndarray, stride: int, counts: np.ndarray,
                    band: int, start: int, stop: int) -> None:
    """``|p + q − w − b|`` of every ``stride``-th pair (the first included) at the model
    pixels (:func:`model_levels`) of the sampled rows ``start`` to ``stop`` counted per bin
    into ``counts[band]`` (B, bins, width) (integers; from width − 1 on into the last column).

    A model pixel's bin is the one whose ranks end after its rank (``ends``, cumulative)
    among the model pixels ordered by level, equal levels in raster order as a stable sort
    orders them: ``first_rank[band]`` holds each level's first rank in this band (its first
    rank in the image plus its pixels in the bands above). A level's ranks grow pixel by
    pixel, so each level keeps the bin its last pixel fell in and moves on from there (a bin
    search from the first bin for every pixel was a third of the noise model's time). Each
    row's model pixels are listed with their bins first, then read two pairs at a time (four
    streams; a test per pixel and pair, taken half the time and mispredicted, cost as much as
    the reading; two pairs a loop, 4.9 → 4.5 ms the noise model of the bench view)."""
    last = counts.shape[2] - 1
    out = counts[band]
    rank = first_rank[band].copy()  # each level's next rank
    level_bin = np.empty(rank.shape[0], np.int64)
    j = 0
    for v in range(rank.shape[0]):  # the first ranks grow with the level
        while j < ends.shape[0] - 1 and ends[j] <= rank[v]:
            j += 1
        level_bin[v] = j
    n_x = (stack.shape[2] + 1) // 2
    xs = np.empty(n_x, np.int64)
    bin_of = np.empty(n_x, np.int64)
    base = np.empty(n_x, np.float32)
    for sy in range(start, stop):
        y = 2 * sy
        m = 0
        for x in range(0, stack.shape[2], 2):
            w = np.float32(stack[0, y, x])
            b = np.float32(stack[1, y, x])
            r = w - b
            if not (r > least and w < most):
                continue
            v = np.int64(r)
            k = level_bin[v]
            while ends[k] <= rank[v]:
                k += 1
            level_bin[v] = k
            rank[v] += 1
            xs[m] = x
            bin_of[m] = k
            base[m] = w + b
            m += 1
        k = 2
        while k + 2 * stride + 1 < stack.shape[0]:  # two pairs at a time
            p, q = stack[k, y], stack[k + 1, y]
            p2, q2 = stack[k + 2 * stride, y], stack[k + 2 * stride + 1, y]
            for i in range(m):
                xi = xs[i]
                r = abs(np.float32(p[xi]) + np.float32(q[xi]) - base[i])
                r2 = abs(np.float32(p2[xi]) + np.float32(q2[xi]) - base[i])
                row = out[bin_of[i]]
                row[min(np.int64(r), last)] += 1
                row[min(np.int64(r2), last)] += 1
            k += 4 * stride
        if k < stack.shape[0] - 1:
            p, q = stack[k, y], stack[k + 1, y]
            for i in range(m):
                r = abs(np.float32(p[xs[i]]) + np.float32(q[xs[i]]) - base[i])
                out[bin_of[i], min(np.int64(r), last)] += 1
