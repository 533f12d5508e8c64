"""The gray-code decoder as it was before issue 16 part 2 (commit 44cb709), frozen: the reference
the fast decoder (:mod:`dotshell_codings.graycode`) is checked against, bit for bit on the
integer codes (``tests/test_decode_reference.py``), and the "before" side of ``make bench``'s
decoder timings. Benchmarks and tests only; nothing in the product imports it.

The original module docstring follows.

Gray-code structured light with pattern/inverse pairs and sub-pixel stripe-edge refinement.

Sequence (for ``axes = "both"``)::

    white, black, col_00, col_00_inv, ..., col_{n-1}, col_{n-1}_inv, row_00, row_00_inv, ...

Bits are projected most significant first. For a projector axis of ``N`` pixels the code has
``n = ceil(log2 N)`` bits and is *centred*: projector pixel ``c`` carries the Gray code of
``v = c + (2**n - N) // 2``, so the code's mirror-symmetric stripe structure sits in the middle
of the projector. ``drop_low_bits = m`` leaves out the ``m`` finest bits; the decoded value is
then the coarse code ``v >> m``, i.e. a block of ``2**m`` projector pixels.

Decoding (all vectorised, one pass per bit):

* bit = pattern > inverse (or pattern > (white + black) / 2 without inverses);
* ``shadow``: white - black < ``shadow_threshold`` * full scale;
* ``low_contrast``: a bit whose contrast (|pattern - inverse| / (white - black), or
  2 |pattern - (white + black)/2| / (white - black) without inverses) is below
  ``min_contrast``. One weak bit is tolerated when flipping it changes the decoded value by
  exactly one code step: the pixel then lies on that bit's stripe edge, where the contrast
  is necessarily zero, and the worst case is the +-1 ambiguity integer decoding has anyway
  (the sub-pixel step then places it between the edges). "On the edge" is checked: the pixel
  needs a 4-neighbour where that bit is strongly positive and one where it is strongly
  negative, so a bit that is weak everywhere (blur, scattering) still marks low_contrast;
* ``out_of_range``: the decoded block does not overlap ``[0, N)``.

That is ``classification = "contrast"``. With ``"robust"`` (the default) each bit is decided by
the Xu & Aliaga rule after a direct/global separation (:mod:`dotshell_codings.robust`, see
docs/codings.md), undecidable bits are *uncertain* instead of weak, and such pixels count as
``uncertain``.

Sub-pixel refinement (``subpixel = true``), for columns and rows alike: each axis is scanned
along the image direction in which its code changes more often (camera rows when its stripes
stand closer to the image columns, camera columns otherwise — so a projector turned 90° or a
projector above the camera refines as well as one beside it), and along the other direction too
where the first leaves more than 5 % of the decoded pixels unrefined (stripes at an angle).
Along a scan line, between two adjacent valid pixels whose codes differ by one step, exactly
one Gray bit flips; the zero crossing of that bit's difference signal ``d`` gives the camera position of the
projector boundary ``c + 0.5``. Where codes differ by two steps (camera coarser than the
projector) the two flipping bits each give a crossing and their mean is an anchor at the centre
of the skipped projector pixel. Every valid pixel with an anchor on each side (within its run of
valid pixels, anchors at most two code steps apart) gets its coordinate by linear
interpolation between them; others keep the integer value.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator, Sequence

import cv2
import numpy as np

from dotshell.coding import Correspondence, PatternFrame, label_reasons
# the settings, the code geometry (bits, offsets, axes) and the levels record are the live
# module's; what is frozen here is the decoding itself (with its per-axis record)
from dotshell_codings.graycode import (_MAX_SUBPIXEL_SPAN, AUTO_DIRECT_MIN_SIGMAS,
                                       SECOND_PASS_SHARE, SETTINGS_SCHEMA, FrameLevels, _Axis,
                                       _gray_to_binary)
from dotshell_codings.robust import direct_global, full_scale, noise_sigma, robust_bits
from dotshell_codings.xor import BASE_FROM_END, _unxor  # the XOR rule itself, unchanged

_CROSS = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))


@dataclass
class AxisDecode:
    """Integer decoding of one projector axis (as the decoder before part 2 kept it)."""

    axis: _Axis
    first_pair: int  # index of the axis' first pattern (pair) after white and black
    code: np.ndarray  # int32 coarse code value per pixel
    integer: np.ndarray  # float32 projector coordinate of the decoded block's centre (clipped)
    weak: np.ndarray  # a weak/uncertain bit that is not tolerated
    tolerated: np.ndarray
    out_of_range: np.ndarray


class GrayCode:
    """Gray-code :class:`dotshell.coding.PatternCoding`; keyword arguments as the settings.

    Subclasses change what is projected for each code bit (:meth:`projected_stripes`) and how
    projected bits turn back into Gray bits (:meth:`gray_bits`)."""

    label = "gray code"

    def __init__(self, axes: str = "both", inverse: bool = True, min_contrast: float = 0.1,
                 shadow_threshold: float = 0.03, drop_low_bits: int = 0, subpixel: bool = True,
                 bit_depth: int = 0, classification: str = "robust", direct_min: float = 0.0,
                 high_frequency_pairs: int = 2, black_level: float = 0.0,
                 centred: bool = True) -> None:
        if axes not in ("columns", "both"):
            raise ValueError(f"axes must be 'columns' or 'both', not {axes!r}")
        if classification not in ("contrast", "robust"):
            raise ValueError(f"classification must be 'contrast' or 'robust', not "
                             f"{classification!r}")
        if classification == "robust" and not inverse:
            classification = "contrast"  # the rule needs inverses; see the setting's help
        self.axes = axes
        self.inverse = bool(inverse)
        self.min_contrast = float(min_contrast)
        self.shadow_threshold = float(shadow_threshold)
        self.drop_low_bits = int(drop_low_bits)
        self.subpixel = bool(subpixel)
        self.bit_depth = int(bit_depth)
        self.classification = classification
        self.direct_min = float(direct_min)
        self.high_frequency_pairs = int(high_frequency_pairs)
        self.black_level = float(black_level)
        self.centred = bool(centred)

    # ---- patterns ------------------------------------------------------------------------

    def _axes(self, projector_size: tuple[int, int]) -> list[_Axis]:
        w, h = (int(s) for s in projector_size)
        axes = [_Axis("col", w, self.drop_low_bits, self.centred)]
        if self.axes == "both":
            axes.append(_Axis("row", h, self.drop_low_bits, self.centred))
        return axes

    def projected_stripes(self, ax: _Axis, i: int) -> np.ndarray:
        """uint8 0/1 vector over the projector axis: what is projected for code bit ``i``."""
        return ax.bit_stripes(i)

    def frame_names(self, projector_size: tuple[int, int]) -> list[str]:
        """Names of :meth:`patterns`, without rendering them."""
        names = ["white", "black"]
        for ax in self._axes(projector_size):
            for name in ax.names():
                if self.inverse or not name.endswith("_inv"):
                    names.append(name)
        return names

    def patterns(self, projector_size: tuple[int, int]) -> list[PatternFrame]:
        w, h = (int(s) for s in projector_size)
        frames = [PatternFrame("white", np.full((h, w), 255, np.uint8)),
                  PatternFrame("black", np.zeros((h, w), np.uint8))]
        for ax in self._axes(projector_size):
            for i in range(ax.nb):
                s = self.projected_stripes(ax, i) * np.uint8(255)
                img = np.broadcast_to(s[None, :] if ax.prefix == "col" else s[:, None], (h, w))
                name = f"{ax.prefix}_{i:02d}"
                frames.append(PatternFrame(name, np.ascontiguousarray(img)))
                if self.inverse:
                    frames.append(PatternFrame(name + "_inv", np.ascontiguousarray(255 - img)))
        return frames

    # ---- decoding ------------------------------------------------------------------------

    def levels(self, white: np.ndarray, black: np.ndarray) -> FrameLevels:
        """Shadow mask, full scale and noise floor from the white and black frames."""
        full = full_scale(white, self.bit_depth)
        w = white.astype(np.float32)
        b = black.astype(np.float32)
        rng = w - b
        if not np.issubdtype(white.dtype, np.integer):
            rng = np.nan_to_num(rng, nan=0.0, posinf=0.0, neginf=0.0)
        return FrameLevels(b, rng, rng < self.shadow_threshold * full, full, noise_sigma(black))

    def _check_frames(self, frames: Sequence[np.ndarray], axes: list[_Axis]) -> list[np.ndarray]:
        per_bit = 2 if self.inverse else 1
        expected = 2 + per_bit * sum(ax.nb for ax in axes)
        if len(frames) != expected:
            raise ValueError(f"{self.label} expects {expected} frames for projector "
                             f"{tuple(ax.size for ax in axes)}, got {len(frames)}")
        frames = [np.asarray(f) for f in frames]
        shape = frames[0].shape
        if len(shape) != 2 or any(f.shape != shape for f in frames):
            raise ValueError("frames must be 2-D arrays of one shape")
        if not np.issubdtype(frames[0].dtype, np.integer):
            frames = [np.nan_to_num(f.astype(np.float32, copy=False)) for f in frames]
        return frames

    def decode(self, frames: Sequence[np.ndarray], projector_size: tuple[int, int]) -> Correspondence:
        axes = self._axes(projector_size)
        frames = self._check_frames(frames, axes)
        lv = self.levels(frames[0], frames[1])
        pairs = _Pairs(frames, self.inverse, lv)
        classify = self._classifier(pairs, axes, lv)
        decoded = []
        first = 0
        for ax in axes:
            decoded.append(_decode_axis(ax, first, self.gray_bits(ax, first, classify)))
            first += ax.nb
        shadow = lv.shadow
        weak = np.zeros(shadow.shape, bool)
        out_of_range = np.zeros(shadow.shape, bool)
        for d in decoded:
            weak |= d.weak
            out_of_range |= d.out_of_range
        uncertain = np.zeros(shadow.shape, bool)
        if self.classification == "robust":
            uncertain = (weak | classify.no_direct) & ~shadow
            low_contrast = np.zeros(shadow.shape, bool)
        else:
            low_contrast = weak & ~shadow
        out_of_range &= ~(shadow | low_contrast | uncertain)
        valid = ~(shadow | low_contrast | uncertain | out_of_range)
        coords, refined = self._coordinates(decoded, valid, pairs)
        tolerated = np.zeros(shadow.shape, bool)
        for d in decoded:
            tolerated |= d.tolerated
        stats = {
            "pixels": int(valid.size),
            "decoded": int(valid.sum()),
            "shadow": int(shadow.sum()),
            "low_contrast": int(low_contrast.sum()),
            "uncertain": int(uncertain.sum()),
            "out_of_range": int(out_of_range.sum()),
            "edge_tolerated": int((tolerated & valid).sum()),
        }
        stats.update(refined)
        masks = {"shadow": shadow, "low_contrast": low_contrast, "uncertain": uncertain,
                 "out_of_range": out_of_range}
        if self.classification == "robust":
            del masks["low_contrast"]
        else:
            del masks["uncertain"]
        reason, names = label_reasons(valid, masks)
        return Correspondence(column=coords[0], row=coords[1] if len(coords) > 1 else None,
                              valid=valid, stats=stats, reason=reason, reason_names=names)

    def _classifier(self, pairs: "_Pairs", axes: list[_Axis], lv: FrameLevels) -> "_Classifier":
        if self.classification == "contrast":
            return _ContrastClassifier(pairs, self.min_contrast, lv)
        sep_pairs: list[int] = []
        high: set[int] = set()
        first = 0
        for ax in axes:
            k = min(self.high_frequency_pairs, ax.nb)
            sep_pairs += list(range(first + ax.nb - k, first + ax.nb))
            high |= {first + i for i in self.high_frequency_bits(ax)}
            first += ax.nb
        ld, lg = direct_global([f for k in sep_pairs for f in pairs.black_subtracted(k)],
                               self.black_level)
        m = (self.direct_min * lv.full_scale if self.direct_min > 0
             else AUTO_DIRECT_MIN_SIGMAS * lv.noise)
        return _RobustClassifier(pairs, ld, lg, m, high | set(sep_pairs), self.min_contrast)

    def high_frequency_bits(self, ax: _Axis) -> list[int]:
        """Projected bits (MSB-first indices) in which global light is the same in pattern and
        inverse: the ``high_frequency_pairs`` finest (the separation's own pairs)."""
        return list(range(ax.nb - min(self.high_frequency_pairs, ax.nb), ax.nb))

    def gray_bits(self, ax: _Axis, first: int, classify: "_Classifier",
                  ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """(value, weak) of each Gray bit of ``ax``, most significant first."""
        for i in range(ax.nb):
            yield classify(first + i)

    def refine_anchors(self, ax: _Axis) -> tuple[int | None, int]:
        """(bit whose stripe edges anchor the sub-pixel step or None for all, max anchor
        spacing in code steps)."""
        return None, _MAX_SUBPIXEL_SPAN

    def _coordinates(self, decoded: list[AxisDecode], valid: np.ndarray, pairs: "_Pairs",
                     ) -> tuple[list[np.ndarray], dict[str, int]]:
        coords = []
        refined: dict[str, int] = {}
        for d in decoded:
            coord = d.integer.astype(np.float32)
            if self.subpixel:
                fine, ok = self._refine_axis(d, valid, pairs)
                coord = np.where(ok, fine, coord).astype(np.float32)
                refined[f"refined_{'column' if d.axis.prefix == 'col' else 'row'}"] = int(ok.sum())
            coord[~valid] = np.nan
            coords.append(coord)
        return coords, refined

    def _refine_axis(self, d: AxisDecode, valid: np.ndarray, pairs: "_Pairs",
                     ) -> tuple[np.ndarray, np.ndarray]:
        """Sub-pixel coordinates of one axis and where they exist: scanned along the image
        direction its stripes cross, then along the other where that leaves more than
        :data:`SECOND_PASS_SHARE` of the decoded pixels unrefined."""
        anchor, span = self.refine_anchors(d.axis)

        def refine(transpose: bool) -> tuple[np.ndarray, np.ndarray]:
            return _refine(d.axis, d.code, valid, transpose,
                           lambda i, flat, step: pairs.d_at(d.first_pair + i, flat, step),
                           anchor, span)

        across = stripes_cross_columns(d.code, valid)
        fine, ok = refine(across)
        left = valid & ~ok
        if left.sum() > SECOND_PASS_SHARE * max(int(valid.sum()), 1):
            fine2, ok2 = refine(not across)
            more = left & ok2
            fine, ok = np.where(more, fine2, fine), ok | more
        return fine, ok


class _Pairs:
    """Access to the pattern/inverse frames (or pattern and per-pixel mid-level) of a view."""

    def __init__(self, frames: list[np.ndarray], inverse: bool, lv: FrameLevels) -> None:
        self.frames = frames
        self.inverse = inverse
        self.per_bit = 2 if inverse else 1
        self.lv = lv
        self.mid = None if inverse else lv.black + 0.5 * lv.range
        self.flat = [f.reshape(-1) for f in frames]
        self.flat_mid = None if self.mid is None else self.mid.reshape(-1)
        self.flat_rng = lv.range.reshape(-1)

    def pattern(self, k: int) -> np.ndarray:
        return self.frames[2 + self.per_bit * k]

    def d(self, k: int) -> np.ndarray:
        """Difference signal of pattern k: pattern − inverse (or pattern − mid)."""
        p = self.pattern(k).astype(np.float32)
        if self.inverse:
            return p - self.frames[3 + self.per_bit * k].astype(np.float32)
        return p - self.mid

    def black_subtracted(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Pattern k and its inverse minus the black frame (float32)."""
        return (self.pattern(k).astype(np.float32) - self.lv.black,
                self.frames[3 + self.per_bit * k].astype(np.float32) - self.lv.black)

    def d_at(self, k: int, flat: np.ndarray, step: int) -> tuple[np.ndarray, np.ndarray]:
        """Range-normalised difference signal of pattern k at flat indices flat and
        flat + step (albedo steps don't move the edge)."""
        p = self.flat[2 + self.per_bit * k]
        q = self.flat[3 + self.per_bit * k] if self.inverse else self.flat_mid
        both = np.concatenate([flat, flat + step])
        d = p[both].astype(np.float32) - q[both].astype(np.float32)
        d /= np.maximum(self.flat_rng[both], np.float32(1e-6))
        return d[:flat.size], d[flat.size:]


class _Classifier:
    """Decides projected pattern k per pixel: ``(value, weak)`` bool arrays."""

    no_direct: np.ndarray | bool = False

    def __call__(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError


class _ContrastClassifier(_Classifier):
    """value = d > 0; weak where |d| < min_contrast × (white − black) (half that without
    inverses, where d = pattern − mid swings half as far)."""

    def __init__(self, pairs: _Pairs, min_contrast: float, lv: FrameLevels) -> None:
        self.pairs = pairs
        self.thr = (min_contrast * (1.0 if pairs.inverse else 0.5)) * np.maximum(lv.range, 0.0)

    def __call__(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        d = self.pairs.d(k)
        return d > 0, np.abs(d) < self.thr


class _RobustClassifier(_Classifier):
    """Xu & Aliaga's rule on black-subtracted frames; weak = uncertain.

    High-frequency pairs (the separation's own pairs; every pair of an XOR code) get the
    rule's ``L_d > L_g`` branch whatever ``L_g``: in them global light is by construction the
    same in pattern and inverse (what the separation assumes), so it cannot flip the
    comparison, while the interval tests would reject every blurred pixel near their dense
    edges. Their bit is uncertain where ``|p − i| < min_contrast · L_d`` — a contrast test
    relative to the direct light, so it neither rejects everything when global light fills the
    white frame nor lets noise decide in a faint PDI image."""

    def __init__(self, pairs: _Pairs, ld: np.ndarray, lg: np.ndarray, m: float,
                 high_frequency: set[int], min_contrast: float) -> None:
        self.pairs = pairs
        self.ld, self.lg, self.m = ld, lg, m
        self.no_direct = ld < m
        self.high_frequency = high_frequency
        self.thr = min_contrast * ld

    def __call__(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        p, q = self.pairs.black_subtracted(k)
        if k in self.high_frequency:
            d = p - q
            return d > 0, self.no_direct | (np.abs(d) < self.thr)
        return robust_bits(p, q, self.ld, self.lg, self.m)


def _decode_axis(ax: _Axis, first: int, bits: Iterable[tuple[np.ndarray, np.ndarray]],
                 ) -> AxisDecode:
    """Assemble Gray bits (value, weak), MSB first, into the coarse code of one axis.

    A single weak bit is harmless when flipping it moves the code by one step and the pixel
    is on that bit's stripe edge (a 4-neighbour where the bit is surely 1 and one where it is
    surely 0); more weak bits, or one off its edge, make the pixel ``weak``."""
    gray = None
    for i, (value, weak) in enumerate(bits):
        if gray is None:
            shape = value.shape
            gray = np.zeros(shape, np.int32)
            n_weak = np.zeros(shape, np.uint8)
            n_weak_edge = np.zeros(shape, np.uint8)
            weak_bit = np.zeros(shape, np.int32)
        gray <<= 1
        gray |= value
        n_weak += weak
        np.copyto(weak_bit, i, where=weak)
        pos = cv2.dilate((value & ~weak).view(np.uint8), _CROSS)
        neg = cv2.dilate((~value & ~weak).view(np.uint8), _CROSS)
        n_weak_edge += weak & (pos & neg).view(bool)
    code = _gray_to_binary(gray)
    k = (ax.nb - 1) - weak_bit  # the weak bit's position from the LSB
    flipped = code ^ ((np.int32(2) << k) - 1)
    edge_ok = (n_weak == 1) & (n_weak_edge == 1) & (np.abs(flipped - code) == 1)
    lo, hi = ax.block_range(code)
    oor = (hi < 0) | (lo > ax.size - 1)
    integer = 0.5 * (np.maximum(lo, 0) + np.minimum(hi, ax.size - 1))
    return AxisDecode(ax, first, code, integer, (n_weak > 0) & ~edge_ok, edge_ok, oor)


def stripes_cross_columns(code: np.ndarray, valid: np.ndarray) -> bool:
    """True when the decoded code changes more often down the camera columns than along the
    camera rows, i.e. the stripes lie closer to the image rows (refine along the columns)."""
    along_rows = np.count_nonzero((code[:, 1:] != code[:, :-1]) & valid[:, 1:] & valid[:, :-1])
    along_cols = np.count_nonzero((code[1:] != code[:-1]) & valid[1:] & valid[:-1])
    return along_cols > along_rows


def _refine(ax: _Axis, code: np.ndarray, valid: np.ndarray, transpose: bool,
            pair_d: Callable[[int, np.ndarray, int], tuple[np.ndarray, np.ndarray]],
            anchor_bit: int | None = None, max_span: int = _MAX_SUBPIXEL_SPAN,
            ) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel coordinates along the camera rows (``transpose``: along the camera columns).

    ``code`` and ``valid`` are in camera layout (H, W). ``pair_d(i, flat, step)`` returns the
    difference signal of projected bit ``i`` at flat pixel indices ``flat`` and ``flat + step``.
    ``anchor_bit``: use only the stripe edges of this bit (one-step code changes where it
    flips), anchors then up to ``max_span`` code steps apart; None: every edge.
    Returns (coordinate, refined mask) in camera layout.
    """
    H, W = code.shape
    if transpose:
        code_l, valid_l, stride, other = np.ascontiguousarray(code.T), np.ascontiguousarray(valid.T), W, 1
    else:
        code_l, valid_l, stride, other = code, valid, 1, W
    h, w = code_l.shape  # lines x samples along the line
    if w < 2:
        return np.zeros(code.shape, np.float32), np.zeros(code.shape, bool)
    a, b = code_l[:, :-1], code_l[:, 1:]
    pair_ok = valid_l[:, :-1] & valid_l[:, 1:]
    step = np.abs(b - a)
    lo = np.minimum(a, b)
    anchor_pos = np.full(a.shape, np.nan, np.float32)
    anchor_val = np.full(a.shape, np.nan, np.float32)
    # projected bit (MSB-first index) that flips on entering coarse code j: lowest set bit of j
    j_all = np.arange(1 << ax.nb, dtype=np.int64)
    low = np.maximum(j_all & -j_all, 1)
    flip_bit = ((ax.nb - 1) - np.round(np.log2(low)).astype(np.int64)).astype(np.uint8)

    def crossings(line: np.ndarray, idx: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Sub-pixel offsets in [0, 1] past sample ``idx`` where the bit flipping on entering
        code ``j`` changes sign."""
        bit = flip_bit[np.minimum(j, len(flip_bit) - 1)]
        order = np.argsort(bit, kind="stable")
        counts = np.bincount(bit, minlength=ax.nb)
        flat = (line * other + idx * stride)[order]
        t = np.empty(line.shape, np.float32)
        start = 0
        for i, n in enumerate(counts):
            if n == 0:
                continue
            sel = order[start:start + n]
            d0, d1 = pair_d(i, flat[start:start + n], stride)
            start += n
            den = d0 - d1  # d0 and d1 have opposite signs (the decoded bit differs)
            with np.errstate(divide="ignore", invalid="ignore"):
                t[sel] = np.where(den != 0, d0 / den, np.float32(0.5))
        return np.clip(t, 0.0, 1.0)

    for k in (1, 2) if anchor_bit is None else (1,):
        sel_k = pair_ok & (step == k)
        if anchor_bit is not None:
            sel_k &= flip_bit[np.minimum(lo + 1, len(flip_bit) - 1)] == anchor_bit
        line, idx = np.nonzero(sel_k)
        if line.size == 0:
            continue
        base = lo[line, idx].astype(np.int64)
        t = np.zeros(line.shape, np.float32)
        for s in range(1, k + 1):
            t += crossings(line, idx, base + s)
        anchor_pos[line, idx] = idx + t / k
        anchor_val[line, idx] = ax.boundary(base + 1) + 0.5 * (k - 1) * ax.block

    has = ~np.isnan(anchor_pos)
    slots = np.arange(w - 1, dtype=np.int32)
    # slot s sits between samples s and s+1; for sample x the left anchor is the last slot < x,
    # the right anchor the first slot >= x
    left = np.maximum.accumulate(np.where(has, slots, np.int32(-1)), axis=1)
    left = np.concatenate([np.full((h, 1), -1, np.int32), left], axis=1)
    right = np.where(has, slots, np.int32(w))[:, ::-1]
    right = np.minimum.accumulate(right, axis=1)[:, ::-1]
    right = np.concatenate([right, np.full((h, 1), w, np.int32)], axis=1)
    # stay within the run of valid samples
    xs = np.arange(w, dtype=np.int32)
    last_bad = np.maximum.accumulate(np.where(valid_l, np.int32(-1), xs), axis=1)
    next_bad = np.minimum.accumulate(np.where(valid_l, np.int32(w), xs)[:, ::-1], axis=1)[:, ::-1]
    ok = valid_l & (left > last_bad) & (right < next_bad) & (left >= 0) & (right < w - 1)

    li = np.clip(left, 0, w - 2)
    ri = np.clip(right, 0, w - 2)
    pl = np.take_along_axis(anchor_pos, li, axis=1)
    vl = np.take_along_axis(anchor_val, li, axis=1)
    pr = np.take_along_axis(anchor_pos, ri, axis=1)
    vr = np.take_along_axis(anchor_val, ri, axis=1)
    span = vr - vl
    with np.errstate(invalid="ignore", divide="ignore"):
        fine = vl + (xs - pl) / (pr - pl) * span
        ok &= (span != 0) & (np.abs(span) <= max_span * ax.block) & (pr > pl)
        # the pixel's own decoded block must lie between the anchors
        own_lo, own_hi = ax.block_range(code_l)
        centre = 0.5 * (own_lo + own_hi)
        ok &= (centre >= np.minimum(vl, vr)) & (centre <= np.maximum(vl, vr))
    fine = np.where(ok, fine, np.float32(np.nan)).astype(np.float32)
    if transpose:
        return np.ascontiguousarray(fine.T), np.ascontiguousarray(ok.T)
    return fine, ok


def make_graycode(settings: dict[str, Any] | None = None, context: Any = None) -> GrayCode:
    """Backend factory: ``settings`` validated against :data:`SETTINGS_SCHEMA`."""
    s = {name: spec.default for name, spec in SETTINGS_SCHEMA.items()}
    s.update(settings or {})
    return GrayCode(**s)


# ---- XOR codes (plugins/dotshell_codings/xor.py of the same commit) ----

#: base stripe width (projector pixels) → position of the base bit counted from the finest


class XorCode(GrayCode):
    """XOR-02 (``base_stripe_px = 2``) or XOR-04 (``base_stripe_px = 4``) code."""

    def __init__(self, base_stripe_px: int = 4, **settings: Any) -> None:
        if base_stripe_px not in BASE_FROM_END:
            raise ValueError(f"XOR base stripe width must be 2 or 4 projector pixels, not "
                             f"{base_stripe_px}")
        super().__init__(**settings)
        self.base_stripe_px = base_stripe_px
        self.label = f"XOR-0{base_stripe_px} code"

    def base_bit(self, ax: _Axis) -> int:
        """Index (MSB first) of the base bit among the axis' projected bits."""
        b = ax.nb - BASE_FROM_END[self.base_stripe_px]
        if b < 0:
            raise ValueError(f"the {self.label} needs at least {BASE_FROM_END[self.base_stripe_px]}"
                             f" bits on the projector {ax.prefix} axis; use a smaller "
                             "drop_low_bits")
        return b

    def projected_stripes(self, ax: _Axis, i: int) -> np.ndarray:
        b = self.base_bit(ax)
        base = ax.bit_stripes(b)
        return base if i == b else ax.bit_stripes(i) ^ base

    def high_frequency_bits(self, ax: _Axis) -> list[int]:
        """Every projected XOR pattern is high-frequency (that is the point of the code)."""
        return list(range(ax.nb))

    def refine_anchors(self, ax: _Axis) -> tuple[int | None, int]:
        """Only the base's edges: its pattern is a clean square wave, while the other projected
        patterns have stripes as narrow as half the base stripe next to their own edges."""
        return self.base_bit(ax), 1 << BASE_FROM_END[self.base_stripe_px]

    def gray_bits(self, ax: _Axis, first: int, classify: _Classifier,
                  ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        b = self.base_bit(ax)
        base, base_weak = classify(first + b)
        for i in range(ax.nb):
            if i == b:
                yield base, base_weak
                continue
            x, x_weak = classify(first + i)
            yield _unxor(x, x_weak, base, base_weak)


def xor_factory(base_stripe_px: int):
    """Backend factory for the XOR code with the given base stripe width."""
    def make(settings: dict[str, Any] | None = None, context: Any = None) -> XorCode:
        s = {name: spec.default for name, spec in SETTINGS_SCHEMA.items()}
        s.update(settings or {})
        return XorCode(base_stripe_px=base_stripe_px, **s)
    return make
