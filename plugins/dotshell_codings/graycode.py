"""Gray-code structured light with pattern/inverse pairs and sub-pixel stripe-edge refinement.

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

Sub-pixel refinement (``subpixel = true``): along each camera row (columns) or camera column
(rows), between two adjacent valid pixels whose codes differ by one step, exactly one Gray bit
flips; the zero crossing of that bit's difference signal ``d`` gives the camera position of the
projector boundary ``c + 0.5``. Where codes differ by two steps (camera coarser than the
projector) the two flipping bits each give a crossing and their mean is an anchor at the centre
of the skipped projector pixel. Every valid pixel with an anchor on each side (within its run of
valid pixels, anchors at most two code steps apart) gets its coordinate by linear
interpolation between them; others keep the integer value.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Sequence

import cv2
import numpy as np

from dotshell.coding import Correspondence, PatternFrame
from dotshell.settings import Setting

SETTINGS_SCHEMA: dict[str, Setting] = {
    "axes": Setting(
        "str", "both", choices=("columns", "both"),
        help="decode projector columns only, or columns and rows"),
    "inverse": Setting(
        "bool", True,
        help="project each bit with its inverse and compare the pair (robust to albedo and "
             "defocus); false: compare with the per-pixel (white + black) / 2"),
    "min_contrast": Setting(
        "float", 0.1, min=0.0, max=1.0,
        help="minimum |pattern - inverse| as a fraction of the pixel's white - black range "
             "(without inverses: 2 |pattern - mid|); weaker bits mark the pixel low_contrast"),
    "shadow_threshold": Setting(
        "float", 0.03, min=0.0, max=1.0,
        help="minimum white - black as a fraction of the frames' full scale; below it the "
             "pixel is shadow"),
    "drop_low_bits": Setting(
        "int", 0, min=0, max=15,
        help="leave out this many finest bits (each halves the resolution and doubles the "
             "finest stripe width)"),
    "subpixel": Setting(
        "bool", True, help="refine coordinates between sub-pixel stripe-edge positions"),
    "bit_depth": Setting(
        "int", 0, min=0, max=16,
        help="significant bits of the camera frames, for the shadow threshold's full scale; "
             "0 = automatic (8 for uint8; for uint16 the smallest depth holding the white "
             "frame's maximum, at least 8)"),
}

_CROSS = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
_MAX_SUBPIXEL_SPAN = 2  # anchors may be at most this many code steps apart


def code_bits(size: int) -> int:
    """Number of Gray-code bits ``ceil(log2 size)`` for a projector axis of ``size`` pixels."""
    if size < 2:
        raise ValueError(f"projector axis of {size} pixels is too small for a Gray code")
    return int(math.ceil(math.log2(size)))


def code_offset(size: int) -> int:
    """Offset of the centred code: pixel ``c`` carries code value ``c + offset``."""
    return ((1 << code_bits(size)) - size) // 2


def _gray_to_binary(g: np.ndarray) -> np.ndarray:
    b = g.copy()
    shift = 1
    while shift < 32:
        b ^= b >> shift
        shift <<= 1
    return b


class _Axis:
    """Code geometry of one projector axis."""

    def __init__(self, prefix: str, size: int, drop: int) -> None:
        self.prefix = prefix
        self.size = size
        self.n = code_bits(size)
        self.offset = code_offset(size)
        self.drop = drop
        self.nb = self.n - drop
        if self.nb < 1:
            raise ValueError(
                f"drop_low_bits = {drop} leaves no bits for a projector {prefix} axis of "
                f"{size} pixels ({self.n} bits); use at most {self.n - 1}")
        self.block = 1 << drop

    def names(self) -> list[str]:
        out = []
        for i in range(self.nb):
            out += [f"{self.prefix}_{i:02d}", f"{self.prefix}_{i:02d}_inv"]
        return out

    def bit_stripes(self, i: int) -> np.ndarray:
        """uint8 0/1 vector over projector pixels of projected bit ``i`` (MSB first)."""
        v = np.arange(self.size, dtype=np.int64) + self.offset
        g = v ^ (v >> 1)
        return ((g >> (self.n - 1 - i)) & 1).astype(np.uint8)

    def block_range(self, code: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Projector pixel range [lo, hi] of coarse code values (unclipped)."""
        lo = code.astype(np.int64) * self.block - self.offset
        return lo, lo + (self.block - 1)

    def boundary(self, j: np.ndarray) -> np.ndarray:
        """Projector coordinate of the boundary just before coarse code ``j``."""
        return j.astype(np.float64) * self.block - self.offset - 0.5


class GrayCode:
    """Gray-code :class:`dotshell.coding.PatternCoding`; keyword arguments as the settings."""

    def __init__(self, axes: str = "both", inverse: bool = True, min_contrast: float = 0.1,
                 shadow_threshold: float = 0.03, drop_low_bits: int = 0, subpixel: bool = True,
                 bit_depth: int = 0) -> None:
        if axes not in ("columns", "both"):
            raise ValueError(f"axes must be 'columns' or 'both', not {axes!r}")
        self.axes = axes
        self.inverse = bool(inverse)
        self.min_contrast = float(min_contrast)
        self.shadow_threshold = float(shadow_threshold)
        self.drop_low_bits = int(drop_low_bits)
        self.subpixel = bool(subpixel)
        self.bit_depth = int(bit_depth)

    # ---- patterns ------------------------------------------------------------------------

    def _axes(self, projector_size: tuple[int, int]) -> list[_Axis]:
        w, h = (int(s) for s in projector_size)
        axes = [_Axis("col", w, self.drop_low_bits)]
        if self.axes == "both":
            axes.append(_Axis("row", h, self.drop_low_bits))
        return axes

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
                s = ax.bit_stripes(i) * np.uint8(255)
                img = np.broadcast_to(s[None, :] if ax.prefix == "col" else s[:, None], (h, w))
                name = f"{ax.prefix}_{i:02d}"
                frames.append(PatternFrame(name, np.ascontiguousarray(img)))
                if self.inverse:
                    frames.append(PatternFrame(name + "_inv", np.ascontiguousarray(255 - img)))
        return frames

    # ---- decoding ------------------------------------------------------------------------

    def _full_scale(self, white: np.ndarray) -> float:
        if self.bit_depth:
            return float((1 << self.bit_depth) - 1)
        if white.dtype == np.uint8:
            return 255.0
        if np.issubdtype(white.dtype, np.integer):
            peak = int(white.max()) if white.size else 0
            return float((1 << max(8, min(16, peak.bit_length()))) - 1)
        return float(white.max()) if white.size else 1.0

    def decode(self, frames: Sequence[np.ndarray], projector_size: tuple[int, int]) -> Correspondence:
        axes = self._axes(projector_size)
        per_bit = 2 if self.inverse else 1
        expected = 2 + per_bit * sum(ax.nb for ax in axes)
        if len(frames) != expected:
            raise ValueError(f"gray code expects {expected} frames for projector "
                             f"{tuple(projector_size)}, got {len(frames)}")
        frames = [np.asarray(f) for f in frames]
        shape = frames[0].shape
        if len(shape) != 2 or any(f.shape != shape for f in frames):
            raise ValueError("frames must be 2-D arrays of one shape")

        white = frames[0].astype(np.float32)
        black = frames[1].astype(np.float32)
        rng = white - black
        shadow = rng < self.shadow_threshold * self._full_scale(frames[0])
        mid = None if self.inverse else 0.5 * (white + black)
        # contrast test |d| < thr, with d = P - I (or P - mid, which swings half as far)
        thr = (self.min_contrast * (1.0 if self.inverse else 0.5)) * np.maximum(rng, 0.0)
        del white, black

        def diff(k: int) -> np.ndarray:  # difference signal of projected frame-pair k
            p = frames[2 + per_bit * k]
            if self.inverse:
                return p.astype(np.float32) - frames[3 + per_bit * k].astype(np.float32)
            return p.astype(np.float32) - mid

        flat_frames = [f.reshape(-1) for f in frames]
        flat_mid = None if mid is None else mid.reshape(-1)
        flat_rng = rng.reshape(-1)

        def pair_d(k: int, flat: np.ndarray, step: int) -> tuple[np.ndarray, np.ndarray]:
            """Difference signal of frame-pair k at flat indices flat and flat + step."""
            p = flat_frames[2 + per_bit * k]
            q = flat_frames[3 + per_bit * k] if self.inverse else flat_mid
            both = np.concatenate([flat, flat + step])
            d = p[both].astype(np.float32) - q[both].astype(np.float32)
            d /= np.maximum(flat_rng[both], np.float32(1e-6))  # albedo steps don't move the edge
            return d[:flat.size], d[flat.size:]

        low_contrast = np.zeros(shape, bool)
        out_of_range = np.zeros(shape, bool)
        tolerated = np.zeros(shape, bool)
        results = []
        first = 0
        for ax in axes:
            gray = np.zeros(shape, np.int32)
            n_weak = np.zeros(shape, np.uint8)
            n_weak_edge = np.zeros(shape, np.uint8)
            weak_bit = np.zeros(shape, np.int32)
            for i in range(ax.nb):
                d = diff(first + i)
                gray <<= 1
                gray |= d > 0
                weak = np.abs(d) < thr
                n_weak += weak
                np.copyto(weak_bit, i, where=weak)
                # a weak bit is on its own stripe edge when it has a strongly positive and a
                # strongly negative 4-neighbour
                pos = cv2.dilate((d > thr).view(np.uint8), _CROSS)
                neg = cv2.dilate((d < -thr).view(np.uint8), _CROSS)
                n_weak_edge += weak & (pos & neg).view(bool)
            code = _gray_to_binary(gray)
            # a single weak bit is harmless when flipping it moves the code by one step
            k = (ax.nb - 1) - weak_bit  # its position from the LSB
            flipped = code ^ ((np.int32(2) << k) - 1)
            edge_ok = (n_weak == 1) & (n_weak_edge == 1) & (np.abs(flipped - code) == 1)
            weak_px = (n_weak > 0) & ~edge_ok
            tolerated |= edge_ok
            lo, hi = ax.block_range(code)
            oor = (hi < 0) | (lo > ax.size - 1)
            integer = 0.5 * (np.maximum(lo, 0) + np.minimum(hi, ax.size - 1))
            low_contrast |= weak_px
            out_of_range |= oor
            results.append((ax, first, code, integer))
            first += ax.nb

        low_contrast &= ~shadow
        out_of_range &= ~shadow & ~low_contrast
        valid = ~(shadow | low_contrast | out_of_range)

        coords = []
        refined: dict[str, int] = {}
        for ax, first_bit, code, integer in results:
            coord = integer.astype(np.float32)
            if self.subpixel:
                transpose = ax.prefix == "row"
                fine, ok = _refine(ax, code, valid, transpose,
                                   lambda i, flat, step, f=first_bit: pair_d(f + i, flat, step))
                coord = np.where(ok, fine, coord).astype(np.float32)
                refined[f"refined_{'row' if transpose else 'column'}"] = int(ok.sum())
            coord[~valid] = np.nan
            coords.append(coord)

        stats = {
            "pixels": int(valid.size),
            "decoded": int(valid.sum()),
            "shadow": int(shadow.sum()),
            "low_contrast": int(low_contrast.sum()),
            "out_of_range": int(out_of_range.sum()),
            "edge_tolerated": int((tolerated & valid).sum()),
        }
        stats.update(refined)
        return Correspondence(column=coords[0], row=coords[1] if len(coords) > 1 else None,
                              valid=valid, stats=stats)


def _refine(ax: _Axis, code: np.ndarray, valid: np.ndarray, transpose: bool,
            pair_d: Callable[[int, np.ndarray, int], tuple[np.ndarray, np.ndarray]],
            ) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel coordinates along the camera rows (``transpose``: along the camera columns).

    ``code`` and ``valid`` are in camera layout (H, W). ``pair_d(i, flat, step)`` returns the
    difference signal of projected bit ``i`` at flat pixel indices ``flat`` and ``flat + step``.
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

    for k in (1, 2):
        line, idx = np.nonzero(pair_ok & (step == k))
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
        ok &= (span != 0) & (np.abs(span) <= _MAX_SUBPIXEL_SPAN * ax.block) & (pr > pl)
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
