"""Gray-code structured light with pattern/inverse pairs and sub-pixel stripe-edge refinement.

Sequence (for ``axes = "both"``)::

    white, black, col_00, col_00_inv, ..., col_{n-1}, col_{n-1}_inv, row_00, row_00_inv, ...

Bits are projected most significant first. For a projector axis of ``N`` pixels the code has
``n = ceil(log2 N)`` bits and is *centred*: projector pixel ``c`` carries the Gray code of
``v = c + (2**n - N) // 2``, so the code's mirror-symmetric stripe structure sits in the middle
of the projector. ``drop_low_bits = m`` leaves out the ``m`` finest bits; the decoded value is
then the coarse code ``v >> m``, i.e. a block of ``2**m`` projector pixels.

Decoding (per pixel, in one compiled pass over the view: :mod:`dotshell_codings.kernels`):

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

That is ``classification = "contrast"``. With ``"robust"`` each bit is decided by
the Xu & Aliaga rule after a direct/global separation (:mod:`dotshell_codings.robust`, see
docs/codings.md), undecidable bits are *uncertain* instead of weak, and such pixels count as
``uncertain``. ``"adaptive"`` (the default) gives those pixels a second chance: decoded by the
signs of their bits where the camera noise model and the separation's bound say the signs are
sure (:func:`kernels._rescue_row`).

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

import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from dotshell.coding import Correspondence, PatternFrame
from dotshell.runtime import hugepages
from dotshell.settings import Setting
from dotshell.runtime.parallel import bands, split, split_bands_joined
from dotshell_codings.robust import full_scale, noise_sigma

SETTINGS_SCHEMA: dict[str, Setting] = {
    "axes": Setting(
        "str", "both", choices=("columns", "both"),
        help="decode projector columns only, or columns and rows"),
    "inverse": Setting(
        "bool", True,
        help="project each bit with its inverse and compare the pair (robust to albedo and "
             "defocus); false: compare with the per-pixel (white + black) / 2"),
    "classification": Setting(
        "str", "adaptive", choices=("contrast", "robust", "adaptive"),
        help="how each bit is decided: 'contrast' = pattern > inverse, bits weaker than "
             "min_contrast mark the pixel low_contrast; 'robust' = Xu & Aliaga's rule with "
             "direct/global separation (bit decided or uncertain); 'adaptive' (the gray "
             "code's default) = robust, and a pixel robust leaves uncertain is decoded as "
             "'contrast' decodes it when all its bits but one also stand out of the camera "
             "noise by adaptive_sigmas (the noise model is measured from the frames) and "
             "beyond what global light "
             "could do, flipping the one that does not moves the code by one step (robust's "
             "edge tolerance), it is not beside a white - black edge (adaptive_edge_ratio) "
             "and its code is continuous with its neighbours' (adaptive_code_steps); "
             "without inverses 'contrast' is used"),
    "adaptive_sigmas": Setting(
        "float", 6.0, min=1.0,
        help="adaptive classification: the least |pattern - inverse| of a pixel's bits (all "
             "but its weakest) in noise sigmas for a pixel robust leaves uncertain to be "
             "decoded"),
    "adaptive_edge_ratio": Setting(
        "float", 0.7, min=0.0, max=1.0,
        help="adaptive classification: a pixel robust leaves uncertain is not decoded when "
             "one of its 8 neighbours has white - black below this fraction of its own (a "
             "silhouette, shadow or depth edge, where a pixel mixes surfaces); 0 = no test"),
    "adaptive_code_steps": Setting(
        "int", 3, min=0,
        help="adaptive classification: a pixel robust leaves uncertain is not decoded when "
             "one of its 8 neighbours' codes (every bit by its sign) lies more than this many "
             "code steps from its own (a surface seen edge-on, a depth edge); 0 = no test"),
    "min_contrast": Setting(
        "float", 0.1, min=0.0, max=1.0,
        help="contrast classification: minimum |pattern - inverse| as a fraction of the "
             "pixel's white - black range (without inverses: 2 |pattern - mid|), weaker bits "
             "mark the pixel low_contrast; robust and adaptive: the finest pairs' minimum "
             "|pattern - inverse| as a fraction of the direct light L_d (weaker: uncertain)"),
    "direct_min": Setting(
        "float", 0.0, min=0.0, max=1.0,
        help="robust classification: minimum direct light L_d as a fraction of full scale; "
             "below it every bit is uncertain. 0 = adaptive: 8 x the camera noise sigma "
             "estimated from the black frame"),
    "high_frequency_pairs": Setting(
        "int", 2, min=1, max=8,
        help="robust classification: the k finest pattern/inverse pairs of each axis used "
             "for the direct/global separation"),
    "black_level": Setting(
        "float", 0.0, min=0.0, max=0.5,
        help="robust classification: projector black level b relative to white as it "
             "remains in the frames after the captured black frame is subtracted (0: the "
             "black frame already carries it)"),
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
    "centred": Setting(
        "bool", True,
        help="centre the code on the projector (pixel c carries code c + (2**n - N) // 2); "
             "false: pixel c carries code c, as SLStudio and OpenCV's GrayCodePattern do"),
    "bit_depth": Setting(
        "int", 0, min=0, max=16,
        help="significant bits of the camera frames, for the shadow threshold's full scale; "
             "0 = automatic (8 for uint8; for uint16 the smallest depth holding the white "
             "frame's maximum, at least 8; float32 frames: the white frame's 99.5th "
             "percentile)"),
}

#: robust classification with direct_min = 0: L_d must exceed this many noise sigmas
AUTO_DIRECT_MIN_SIGMAS = 8.0
_MAX_SUBPIXEL_SPAN = 2  # anchors may be at most this many code steps apart
#: refine along the second image direction too when the first leaves more than this share of
#: the decoded pixels unrefined (stripes at an angle, curved stripes)
SECOND_PASS_SHARE = 0.05


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

    def __init__(self, prefix: str, size: int, drop: int, centred: bool = True) -> None:
        self.prefix = prefix
        self.size = size
        self.n = code_bits(size)
        self.offset = code_offset(size) if centred else 0
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


@dataclass
class FrameLevels:
    """Per-pixel levels of one view, from its white and black frames.

    Attributes:
        black: float32 black frame (subtracted before the robust classification).
        range: float32 white - black.
        shadow: bool, white - black below ``shadow_threshold`` × ``full_scale``.
        full_scale: the frames' full-scale value (see :func:`robust.full_scale`).
        noise: camera noise σ from the black frame (frame units).
    """

    black: np.ndarray
    range: np.ndarray
    shadow: np.ndarray
    full_scale: float
    noise: float


@dataclass
class AxisDecode:
    """Integer decoding of one projector axis."""

    axis: _Axis
    first_pair: int  # index of the axis' first pattern (pair) after white and black
    code: np.ndarray  # int32 coarse code value per pixel
    integer: np.ndarray  # float32 projector coordinate of the decoded block's centre (clipped)


class GrayCode:
    """Gray-code :class:`dotshell.coding.PatternCoding`; keyword arguments as the settings.

    Subclasses change what is projected for each code bit (:meth:`projected_stripes`) and how
    projected bits turn back into Gray bits (:meth:`gray_bits`)."""

    label = "gray code"

    def __init__(self, axes: str = "both", inverse: bool = True, min_contrast: float = 0.1,
                 shadow_threshold: float = 0.03, drop_low_bits: int = 0, subpixel: bool = True,
                 bit_depth: int = 0, classification: str = "adaptive", direct_min: float = 0.0,
                 high_frequency_pairs: int = 2, black_level: float = 0.0,
                 centred: bool = True, adaptive_sigmas: float = 6.0,
                 adaptive_edge_ratio: float = 0.7, adaptive_code_steps: int = 3) -> None:
        if axes not in ("columns", "both"):
            raise ValueError(f"axes must be 'columns' or 'both', not {axes!r}")
        if classification not in ("contrast", "robust", "adaptive"):
            raise ValueError(f"classification must be 'contrast', 'robust' or 'adaptive', not "
                             f"{classification!r}")
        if classification in ("robust", "adaptive") and not inverse:
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
        self.adaptive_sigmas = float(adaptive_sigmas)
        self.adaptive_edge_ratio = float(adaptive_edge_ratio)
        self.adaptive_code_steps = int(adaptive_code_steps)

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

    def _stack(self, frames: Sequence[np.ndarray], axes: list[_Axis]) -> tuple[np.ndarray, float]:
        """The frames as one read-only (F, H, W) array — the caller's stack itself, or a view
        of it when the frames are evenly spaced views of one array (as read from a frame
        stack), else a copy — and their full scale (:func:`robust.full_scale`). Float frames
        get NaN → 0 (and ±inf → the largest float32), as the rule needs; uint8 frames become
        uint16 (exact, and one compiled variant fewer)."""
        per_bit = 2 if self.inverse else 1
        expected = 2 + per_bit * sum(ax.nb for ax in axes)
        if len(frames) != expected:
            raise ValueError(f"{self.label} expects {expected} frames for projector "
                             f"{tuple(ax.size for ax in axes)}, got {len(frames)}")
        stack = as_stack(frames)
        if not np.issubdtype(stack.dtype, np.integer):
            stack = np.nan_to_num(stack.astype(np.float32, copy=False))
        full = full_scale(stack[0], self.bit_depth)
        if stack.dtype == np.uint8:
            stack = stack.astype(np.uint16)
        stack = stack.view()
        stack.flags.writeable = False  # one compiled variant for stacks and views of them
        return stack, full

    def decode(self, frames: Sequence[np.ndarray], projector_size: tuple[int, int]) -> Correspondence:
        axes = self._axes(projector_size)
        stack, full = self._stack(frames, axes)
        rule = self._rule(stack, axes, full)
        words = None
        if type(self).gray_words is not GrayCode.gray_words:
            words = self._classify(stack, rule)
            for a, ax in enumerate(axes):
                words.value[a], words.weak[a] = self.gray_words(ax, words.value[a], words.weak[a])
        adaptive = self._adaptive(frames, stack, axes, full)
        valid, reason, counts, coords, refined = self._decode_rows(stack, axes, rule, words,
                                                                   adaptive)
        n = [int(c) for c in counts.sum(axis=0)]
        poor = "low_contrast" if self.classification == "contrast" else "uncertain"
        stats = {"pixels": int(valid.size), "decoded": n[0], "shadow": n[1], "low_contrast": 0,
                 "uncertain": 0, "out_of_range": n[3], "edge_tolerated": n[4]}
        stats[poor] = n[2]
        if adaptive is not None:
            stats["adaptive_rescued"] = n[5]
            stats["noise_floor"] = round(float(np.sqrt(adaptive.floor)), 3)
            stats["noise_gain"] = round(float(adaptive.gain), 5)
        stats.update(refined)
        return Correspondence(column=coords[0], row=coords[1] if len(coords) > 1 else None,
                              valid=valid, stats=stats, reason=reason,
                              reason_names=("decoded", "shadow", poor, "out_of_range"))

    def _with(self, **changes: Any) -> GrayCode:
        """A copy of this coding with some attributes changed."""
        import copy

        other = copy.copy(self)
        other.__dict__.update(changes)
        return other

    def _adaptive(self, frames: Sequence[np.ndarray], stack: np.ndarray, axes: list[_Axis],
                  full: float) -> Rescue | None:
        """The adaptive classification's second chance for the pixels robust leaves uncertain,
        with the camera noise model measured from the frames (:func:`robust.noise_model`);
        None for the other classifications."""
        if self.classification != "adaptive":
            return None
        from dotshell_codings.robust import noise_model

        integer = np.issubdtype(stack.dtype, np.integer)
        # the stack's full scale is the noise model's where no bit depth set it (integers)
        floor, gain = noise_model(stack if integer else frames,
                                  full if integer and not self.bit_depth else None)
        return Rescue(np.array([self.sign_base(ax) for ax in axes], np.int64),
                      np.array([2 * floor, gain, self.adaptive_sigmas, self.adaptive_edge_ratio,
                                self.adaptive_code_steps], np.float32),
                      floor, gain)

    def sign_base(self, ax: _Axis) -> int:
        """The projected bit (MSB-first index) whose value is XORed into the other projected
        bits of ``ax``, −1 where the projected bits are the Gray bits themselves (the adaptive
        rescue's sign code; :meth:`gray_words` for the decided words)."""
        return -1

    def _decode_rows(self, stack: np.ndarray, axes: list[_Axis], rule: tuple,
                     words: ClassifiedBits | None,
                     adaptive: Rescue | None = None) -> tuple:
        """(valid, reason, per-row counts (H, 6), each axis's coordinates, refined counts)
        from one pass over the view (:func:`kernels.decode_rows`, bands of rows taken by the
        cores one at a time, joined in order, each join as soon as the bands up to it are
        done: :func:`parallel.split_bands_joined`); ``words``: the Gray words, when the projected
        bits are not Gray bits (else they are made in the pass); ``adaptive``:
        :meth:`_adaptive`'s (the pixels robust leaves uncertain get their second chance in
        the same pass).

        Each axis is first refined across its stripes the way its projector axis suggests:
        columns along the camera rows, rows down the camera columns. Where the decoded codes
        change more often the other way (counted in the same pass), the stripes lie the other
        way across the image (a camera turned by 90°): that axis is refined again the other
        way, from the block centres."""
        k = _kernels()
        h, w = stack.shape[1:]
        n_axes = len(axes)
        firsts = np.cumsum([0] + [ax.nb for ax in axes])[:-1]
        settings = np.zeros((n_axes, 6), np.int64)
        tables = [k.flip_table(ax.nb) for ax in axes]
        flips = np.zeros((n_axes, max(len(t) for t in tables)), np.int64)
        for a, ax in enumerate(axes):
            anchor, span = self.refine_anchors(ax)
            settings[a] = (ax.block, ax.offset, ax.size, firsts[a],
                           -1 if anchor is None else anchor, span)
            flips[a, :len(tables[a])] = tables[a]
        down = np.array([ax.prefix != "col" for ax in axes])
        if words is None:
            words = ClassifiedBits(np.empty((n_axes, 0, w), np.uint32),
                                   np.empty((n_axes, 0, w), np.uint32),
                                   hugepages.empty((h, w), np.float32),
                                   hugepages.empty((h, w), bool), hugepages.empty((h, w), bool))
            classified = False
        else:
            classified = True
        code = hugepages.empty((n_axes, h, w), np.int32)
        coord = hugepages.empty((n_axes, h, w), np.float32)
        ok = hugepages.empty((n_axes, h, w), bool)
        valid = hugepages.empty((h, w), bool)
        reason = hugepages.empty((h, w), np.uint8)
        counts = np.empty((h, 6), np.int64)
        changed = np.empty((n_axes, h, 2), np.int64)
        bounds = bands(h, per_worker=DECODE_BANDS_PER_WORKER)
        scan_i = np.empty((len(bounds) - 1, n_axes, 4, w), np.int64)
        scan_f = np.empty((len(bounds) - 1, n_axes, 4, w), np.float32)
        if adaptive is None:
            adaptive_args = (False, np.full(n_axes, -1, np.int64), np.zeros(5, np.float32))
        else:
            adaptive_args = (True, adaptive.bases, adaptive.values)
        args = (*rule, settings, flips, down, self.subpixel, classified, *adaptive_args,
                words.value, words.weak,
                code, coord, ok, valid, reason, counts, changed, words.range, words.shadow,
                words.no_direct, scan_i, scan_f)
        split_bands_joined(k.decode_rows, bounds,
                           lambda band: k.decode_rows(*args, k.JOIN, band, bounds[band],
                                                      bounds[band + 1]), *args, k.BAND)
        refined = {}
        for a, ax in enumerate(axes):
            if not self.subpixel:
                continue
            along_rows, along_cols = changed[a].sum(axis=0)
            across = bool(along_cols > along_rows)
            if across != down[a]:  # refined the wrong way: start again from the block centres
                split(k.block_centres, h, code[a], valid, ax.block, ax.offset, ax.size, coord[a])
            d = AxisDecode(ax, int(firsts[a]), code[a], coord[a])
            refined[f"refined_{_axis_name(ax)}"] = self._refine_axis(
                d, valid, stack, words.range, coord[a], ok[a], tables[a], across,
                done=across == down[a])
        return valid, reason, counts, list(coord), refined

    def _rule(self, stack: np.ndarray, axes: list[_Axis], full: float) -> tuple:
        """The arguments of :func:`kernels.classify` before its outputs: the stack, then the
        levels and thresholds of the rule (``full``: the frames' full scale)."""
        n_pairs = sum(ax.nb for ax in axes)
        sep = np.zeros(n_pairs, bool)
        high = np.zeros(n_pairs, bool)
        first = 0
        for ax in axes:
            k = min(self.high_frequency_pairs, ax.nb)
            sep[first + ax.nb - k:first + ax.nb] = True
            high[[first + i for i in self.high_frequency_bits(ax)]] = True
            first += ax.nb
        high |= sep
        robust = self.classification in ("robust", "adaptive")
        m = 0.0
        if robust:
            m = (self.direct_min * full if self.direct_min > 0
                 else AUTO_DIRECT_MIN_SIGMAS * noise_sigma(stack[1]))
        b = self.black_level
        if not 0.0 <= b < 1.0:
            raise ValueError(f"black level ratio must be in [0, 1), not {b}")
        f32 = np.float32
        k = _kernels()
        return (stack, self.inverse, k.ROBUST if robust else k.CONTRAST,
                np.array([ax.nb for ax in axes], np.int64), sep, high,
                f32(self.shadow_threshold * full), f32(m), f32(self.min_contrast),
                f32(self.min_contrast * (1.0 if self.inverse else 0.5)),
                f32(1.0 - b), f32(2.0 / (1.0 - b * b)), f32(b))

    def _classify(self, stack: np.ndarray, rule: tuple) -> ClassifiedBits:
        """Every projected bit of every pixel decided in one pass over the frames
        (:func:`kernels.classify`; ``rule``: :meth:`_rule`)."""
        n_axes = len(rule[3])
        h, w = stack.shape[1:]
        out = ClassifiedBits(np.empty((n_axes, h, w), np.uint32),
                             np.empty((n_axes, h, w), np.uint32), np.empty((h, w), np.float32),
                             np.empty((h, w), bool), np.empty((h, w), bool))
        split(_kernels().classify, h, *rule, out.value, out.weak, out.range, out.shadow,
              out.no_direct)
        return out

    def high_frequency_bits(self, ax: _Axis) -> list[int]:
        """Projected bits (MSB-first indices) in which global light is the same in pattern and
        inverse: the ``high_frequency_pairs`` finest (the separation's own pairs)."""
        return list(range(ax.nb - min(self.high_frequency_pairs, ax.nb), ax.nb))

    def gray_words(self, ax: _Axis, value: np.ndarray, weak: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Packed Gray bits and weak bits of ``ax`` (bit ``nb - 1 - i`` = bit i, MSB first)
        from the packed projected bits: the same for a gray code."""
        return value, weak

    def refine_anchors(self, ax: _Axis) -> tuple[int | None, int]:
        """(bit whose stripe edges anchor the sub-pixel step or None for all, max anchor
        spacing in code steps)."""
        return None, _MAX_SUBPIXEL_SPAN

    def _refine_axis(self, d: AxisDecode, valid: np.ndarray, stack: np.ndarray,
                     rng: np.ndarray, coord: np.ndarray, ok: np.ndarray, flip: np.ndarray,
                     across: bool, done: bool) -> int:
        """Refine ``coord`` (one axis's coarse coordinates) in place to sub-pixel and set it NaN
        where not decoded; returns how many pixels were refined (marked in ``ok``). Scanned
        along the image direction its stripes cross (down the columns if ``across``: its
        code changes more often down them), then along the other where that leaves more
        than :data:`SECOND_PASS_SHARE` of the decoded pixels unrefined. ``done``: the first
        scan already ran (:func:`kernels.decode_rows`), with ``ok`` its refined pixels.
        ``flip``: the axis's :func:`kernels.flip_table`."""
        anchor, span = self.refine_anchors(d.axis)
        ax = d.axis
        k = _kernels()

        def refine(down: bool, first: bool) -> int:
            kernel = k.refine_columns if down else k.refine_rows
            split(kernel, valid.shape[1] if down else valid.shape[0], stack, self.inverse, rng,
                  d.code, valid, flip, ax.block, ax.offset, d.first_pair,
                  -1 if anchor is None else anchor, span, first, coord, ok)
            return int(np.count_nonzero(ok))

        n_ok = int(np.count_nonzero(ok)) if done else refine(across, True)
        n_valid = int(np.count_nonzero(valid))
        if n_valid - n_ok > SECOND_PASS_SHARE * max(n_valid, 1):
            n_ok = refine(not across, False)
        return n_ok


#: bands of rows per core in the one-pass decode: the cores take them one at a time, so a core
#: whose bands hold fewer lit pixels takes more of them (a view's lit rows are rarely spread
#: evenly: 227 k against 394 k decoded pixels in the halves of the bench view). Each band
#: costs two rows classified again and a join of ~0.1 ms; measured on the bench view (CPU of
#: each band, taken in order by two equal cores), the busier core carried 60 % of the work
#: with 2 bands a core, 56 % with 4, 52 % with 8 and 51 % with 12
DECODE_BANDS_PER_WORKER = 8


def _axis_name(ax: _Axis) -> str:
    return "column" if ax.prefix == "col" else "row"


def _kernels() -> Any:
    """:mod:`dotshell_codings.kernels`, imported at the first decode: numba's import costs
    ~0.5 s and ~110 MiB, which commands that load the plugins without decoding don't pay."""
    from dotshell_codings import kernels

    return kernels


def as_stack(frames: Sequence[np.ndarray]) -> np.ndarray:
    """Frames as one (F, H, W) array without copying when they already are one: a 3-D array
    as is, 2-D frames that are evenly spaced views of one array (a frame stack read from disk,
    split into frames) as a read-only view of it; other frames are copied into a new stack."""
    if isinstance(frames, np.ndarray):
        if frames.ndim != 3:
            raise ValueError("frames must be 2-D arrays of one shape")
        return frames
    frames = [np.asarray(f) for f in frames]
    first = frames[0]
    if first.ndim != 2 or any(f.shape != first.shape for f in frames):
        raise ValueError("frames must be 2-D arrays of one shape")
    view = _stack_view(frames)
    return view if view is not None else np.stack(frames)


def _stack_view(frames: list[np.ndarray]) -> np.ndarray | None:
    first = frames[0]
    base = first.base
    if base is None or len(frames) < 2 or not isinstance(base, np.ndarray):
        return None
    if any(f.base is not base or f.dtype != first.dtype or f.strides != first.strides
           for f in frames):
        return None
    ptr = [f.__array_interface__["data"][0] for f in frames]
    step = ptr[1] - ptr[0]
    if any(b - a != step for a, b in zip(ptr, ptr[1:])):
        return None
    return np.lib.stride_tricks.as_strided(first, (len(frames), *first.shape),
                                           (step, *first.strides), writeable=False)


@dataclass
class Rescue:
    """The adaptive classification's arguments of :func:`kernels.decode_rows`.

    Attributes:
        bases: (axes,) int64, each axis's :meth:`GrayCode.sign_base`.
        values: (5,) float32, ``2 floor``, ``gain``, ``adaptive_sigmas``,
            ``adaptive_edge_ratio`` and ``adaptive_code_steps`` (the kernel's
            :data:`kernels.FLOOR2` …).
        floor, gain: the camera noise model ``var(I) = floor + gain (I − black)`` (frame
            units², :func:`robust.noise_model`).
    """

    bases: np.ndarray
    values: np.ndarray
    floor: float
    gain: float


@dataclass
class ClassifiedBits:
    """Projected bits of a view, decided per pixel (output of :func:`kernels.classify`).

    Attributes:
        value, weak: (axes, H, W) uint32, bit ``nb - 1 - i`` = projected bit i of the axis
            (decided 1; undecided: weak/uncertain).
        range: float32 white − black (frame units).
        shadow: white − black below ``shadow_threshold`` × full scale.
        no_direct: robust rule, direct light below the least usable (False for "contrast").
    """

    value: np.ndarray
    weak: np.ndarray
    range: np.ndarray
    shadow: np.ndarray
    no_direct: np.ndarray


def make_graycode(settings: dict[str, Any] | None = None, context: Any = None) -> GrayCode:
    """Backend factory: ``settings`` validated against :data:`SETTINGS_SCHEMA`."""
    s = {name: spec.default for name, spec in SETTINGS_SCHEMA.items()}
    s.update(settings or {})
    return GrayCode(**s)
