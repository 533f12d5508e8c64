"""Frame levels and bit classification shared by the binary codings (pure functions).

* :func:`full_scale` — the frames' full-scale value (uint8, uint16 by bit depth, float32 by the
  white frame's 99.5th percentile).
* :func:`noise_sigma` — the camera noise floor, estimated from the black frame.
* :func:`direct_global` — per-pixel direct and global light (Nayar et al. 2006) from the
  high-frequency pattern/inverse frames.
* :func:`robust_bits` — the Xu & Aliaga (2007) pixel classification as used by Moreno & Taubin
  (2012): each bit is decided or marked uncertain.

References:
    S. K. Nayar, G. Krishnan, M. D. Grossberg, R. Raskar, "Fast separation of direct and global
    components of a scene using high frequency illumination", ACM SIGGRAPH 2006.
    Y. Xu, D. G. Aliaga, "Robust pixel classification for 3D modeling with structured light",
    Graphics Interface 2007.
    D. Moreno, G. Taubin, "Simple, accurate, and robust projector-camera calibration", 3DIMPVT
    2012.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

#: percentile of the white frame taken as full scale for float frames (PDI differences)
FLOAT_FULL_SCALE_PERCENTILE = 99.5


def full_scale(white: np.ndarray, bit_depth: int = 0) -> float:
    """Full-scale value of camera frames, from their dtype and the white frame.

    ``bit_depth`` > 0 wins (``2**bit_depth - 1``). Otherwise uint8 → 255; other integer types →
    the smallest depth holding the white frame's maximum (at least 8, at most 16 bits); float
    frames (e.g. PDI differences ``|I∥ − I⊥|``, which have no fixed range) → the white frame's
    99.5th percentile, so a few saturated or hot pixels do not set the scale.
    """
    if bit_depth:
        return float((1 << bit_depth) - 1)
    if white.dtype == np.uint8:
        return 255.0
    if np.issubdtype(white.dtype, np.integer):
        peak = int(white.max()) if white.size else 0
        return float((1 << max(8, min(16, peak.bit_length()))) - 1)
    finite = white[np.isfinite(white)]
    if finite.size == 0:
        return 1.0
    top = float(np.percentile(finite, FLOAT_FULL_SCALE_PERCENTILE))
    return top if top > 0 else 1.0


def noise_sigma(black: np.ndarray) -> float:
    """Camera noise σ (frame units) from the black frame: 1.4826 × the median absolute
    deviation of the differences of horizontally adjacent pixels, divided by √2. Differencing
    drops smooth ambient structure; the median ignores edges and hot pixels.

    Integer frames take their medians from a histogram of the differences (exact, the same
    value as ``np.median``; a sort of 1.3 M values took 60 ms, the histogram takes 2)."""
    if np.issubdtype(np.asarray(black).dtype, np.integer) and black.ndim == 2:
        return _noise_sigma_integer(black)
    f = np.asarray(black, dtype=np.float32)
    if f.ndim != 2 or f.shape[1] < 2:
        return 0.0
    diff = (f[:, 1:] - f[:, :-1]).ravel()
    diff = diff[np.isfinite(diff)]
    if diff.size == 0:
        return 0.0
    mad = float(np.median(np.abs(diff - np.median(diff))))
    return 1.4826 * mad / math.sqrt(2.0)


def _noise_sigma_integer(black: np.ndarray) -> float:
    if black.shape[1] < 2 or black.shape[0] == 0:
        return 0.0
    low, counts = difference_histogram(black)
    values = np.nonzero(counts)[0]
    counts = counts[values]
    values = values.astype(np.float64) + low
    med = _median_of_counts(values, counts)
    dev = np.abs(values - med)
    order = np.argsort(dev, kind="stable")
    mad = _median_of_counts(dev[order], counts[order])
    return 1.4826 * mad / math.sqrt(2.0)


def difference_histogram(image: np.ndarray) -> tuple[int, np.ndarray]:
    """(lowest value, counts) of the differences of horizontally adjacent pixels of a 2-D
    integer image (``counts[i]``: how often ``lowest + i`` occurs; the range holds 0), counted
    in bands of rows on every core (:func:`kernels.difference_extremes`,
    :func:`kernels.difference_counts`): the decode waits for it before its passes start."""
    from dotshell.runtime.parallel import bands, split_bands
    from dotshell_codings import kernels  # numba, at first use

    bounds = bands(image.shape[0])
    extremes = np.zeros((len(bounds) - 1, 2), np.int64)
    split_bands(kernels.difference_extremes, bounds, image, extremes)
    low, high = int(extremes[:, 0].min()), int(extremes[:, 1].max())
    counts = np.zeros((len(bounds) - 1, high - low + 1), np.int64)
    split_bands(kernels.difference_counts, bounds, image, low, counts)
    return low, counts.sum(axis=0)


def _median_of_counts(values: np.ndarray, counts: np.ndarray) -> float:
    """The median (as ``np.median``: the mean of the two middle values of an even count) of
    sorted ``values`` each occurring ``counts`` times."""
    n = int(counts.sum())
    ends = np.cumsum(counts)
    lo = values[np.searchsorted(ends, (n - 1) // 2, side="right")]
    hi = values[np.searchsorted(ends, n // 2, side="right")]
    return float(0.5 * (lo + hi))


def direct_global(frames: Sequence[np.ndarray], black_level: float = 0.0,
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Direct ``L_d`` and global ``L_g`` light per pixel (Nayar et al. 2006).

    ``frames`` are black-subtracted float images under high-frequency patterns in which every
    pixel is lit in some frames and unlit in others (pattern/inverse pairs of the finest bits);
    ``black_level`` is the projector's black level ``b`` relative to white as it remains in the
    frames (0 after subtracting the captured black frame). With ``L_max``/``L_min`` the
    per-pixel maximum/minimum over the frames::

        L_d = (L_max − L_min) / (1 − b)        L_g = 2 (L_min − b L_max) / (1 − b²)

    Where ``L_g`` comes out negative (noise, no global light) it is set to 0 and ``L_d`` to
    ``L_max``, as Moreno & Taubin do.
    """
    if not frames:
        raise ValueError("direct/global separation needs at least one frame")
    b = float(black_level)
    if not 0.0 <= b < 1.0:
        raise ValueError(f"black level ratio must be in [0, 1), not {b}")
    lmax = np.array(frames[0], dtype=np.float32, copy=True)
    lmin = lmax.copy()
    for f in frames[1:]:
        np.maximum(lmax, f, out=lmax)
        np.minimum(lmin, f, out=lmin)
    ld = (lmax - lmin) / np.float32(1.0 - b)
    lg = np.float32(2.0 / (1.0 - b * b)) * (lmin - np.float32(b) * lmax)
    neg = lg < 0
    ld[neg] = lmax[neg]
    lg[neg] = 0.0
    return ld, lg


def robust_bits(pattern: np.ndarray, inverse: np.ndarray, ld: np.ndarray, lg: np.ndarray,
                direct_min: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Xu & Aliaga's rule (as in Moreno & Taubin) for one pattern/inverse pair.

    All inputs are black-subtracted intensities of the same units. Per pixel, with
    ``m = direct_min``:

    * ``L_d < m`` → uncertain (too little direct light to decide anything);
    * ``L_d > L_g`` → bit = pattern > inverse;
    * ``pattern ≤ L_d`` and ``inverse ≥ L_g`` → 0;
    * ``pattern ≥ L_g`` and ``inverse ≤ L_d`` → 1;
    * otherwise uncertain.

    Returns ``(bit, uncertain)``, both bool; ``bit`` is False where uncertain.
    """
    p, q = pattern, inverse
    enough = ld >= direct_min
    direct_wins = enough & (ld > lg)
    zero = np.where(direct_wins, p <= q, enough & (p <= ld) & (q >= lg))
    one = np.where(direct_wins, p > q, enough & (p >= lg) & (q <= ld)) & ~zero  # 0 tested first
    return one, ~(one | zero)


#: Noise-model fit: pixels whose white − black is below this share of full scale are left out
#: (shadow), as are those within 1 % of full scale (saturation breaks the identity).
_MODEL_MIN_RANGE = 0.03


def noise_model(frames: Sequence[np.ndarray] | np.ndarray, full: float | None = None
                ) -> tuple[float, float]:
    """The camera's noise, ``var(I) = floor + gain · (I − black)`` (frame units²), measured
    from a pattern/inverse sequence (white, black, then pairs).

    Light adds linearly, so pattern + inverse = white + black at every pixel, global light
    included: ``r = p + q − w − b`` is pure noise with ``var(r) = 4 floor + 2 gain (w − b)``.
    The fit is a line through the medians of ``r²`` (÷ 0.4549, the median of χ²₁) in ten
    equal-count bins of ``w − b`` (ranked stably: equal levels in raster order), on every
    second pixel each way and every :data:`_MODEL_PAIR_STRIDE`-th pair. An 8- or 16-bit (F, H, W) stack is counted in compiled passes
    (:func:`noise_model_counted`, the same figures), anything else sorted
    (:func:`noise_model_sorted`). ``full``: the stack's :func:`full_scale` (of its white
    frame, without a bit depth), when the caller has it (a full-frame maximum less)."""
    if (isinstance(frames, np.ndarray) and frames.ndim == 3
            and frames.dtype in (np.uint8, np.uint16)):
        model = noise_model_counted(frames, full)
        if model is not None:
            return model
    return noise_model_sorted(frames)


def _model_thresholds(white: np.ndarray) -> tuple[float, float]:
    """Noise-model fit: the least ``w − b`` (shadow) and the largest ``w`` (saturation)."""
    return _thresholds_of(full_scale(np.asarray(white)))


def _thresholds_of(top: float) -> tuple[float, float]:
    """:func:`_model_thresholds` from the frames' full scale ``top``."""
    return _MODEL_MIN_RANGE * top, 0.99 * top


def _model_line(xs: Sequence[float], ys: Sequence[float]) -> tuple[float, float]:
    """(floor, gain) from the bins' levels ``w − b`` and medians of ``r²`` / 0.4549."""
    slope, intercept = np.polyfit(xs, ys, 1)
    return max(float(intercept), 0.0) / 4.0, max(float(slope), 0.0) / 2.0


#: the noise model's bins of w − b
_MODEL_BINS = 10
#: the noise model reads every fifth pattern/inverse pair (the first included): ``p + q − w − b``
#: is pure noise in every pair alike, and 4 of a full view's 20 pairs give ~1.3 M residuals,
#: ~130 k a bin, whose medians move by well under 1 %; reading all 20 took 10 ms of the
#: adaptive decode's 40 ms a full-resolution view (issue 32)
_MODEL_PAIR_STRIDE = 5
#: counted noise model: |p + q − w − b| counted one by one up to this (a median beyond it, a
#: noise σ of thousands of frame units, is sorted instead)
_MODEL_MAX_RESIDUAL = 8190


def noise_model_sorted(frames: Sequence[np.ndarray]) -> tuple[float, float]:
    """:func:`noise_model` by sorting (any frame type)."""

    def sub(k: int) -> np.ndarray:
        return np.asarray(frames[k])[::2, ::2].astype(np.float32)

    white, black = sub(0), sub(1)
    rng = white - black
    least, most = _model_thresholds(frames[0])
    ok = (rng > least) & (white < most) & np.isfinite(rng)
    if ok.sum() < 100 or len(frames) < 4:
        return float(noise_sigma(np.asarray(frames[1])) ** 2), 0.0
    level, base = rng[ok], (white + black)[ok]
    order = np.argsort(level, kind="stable")
    sq = np.stack([(sub(k)[ok] + sub(k + 1)[ok] - base) ** 2
                   for k in range(2, len(frames) - 1, 2 * _MODEL_PAIR_STRIDE)],
                  axis=1)[order]
    chunks = np.array_split(np.arange(len(order)), _MODEL_BINS)
    xs = [float(np.median(level[order][c])) for c in chunks]
    ys = [float(np.median(sq[c])) / 0.4549 for c in chunks]
    return _model_line(xs, ys)


def noise_model_counted(stack: np.ndarray, full: float | None = None
                        ) -> tuple[float, float] | None:
    """:func:`noise_model` of an 8- or 16-bit (F, H, W) stack by counting, the same figures as
    :func:`noise_model_sorted` (equal to the last bit, ``tests/test_decode_adaptive.py``): the
    levels ``w − b`` and ``|r|`` are integers, so histograms give the bins (a level's pixels
    ranked in raster order, as a stable sort ranks them) and the medians (``r²`` grows with
    ``|r|``) in two compiled passes over bands of rows on every core (:mod:`kernels`: a sort
    of 1.5 M values and ten medians of 3 M took ~80 ms a full view, these ~3). None when the
    median ``|r|`` is beyond the counted range (then sort). ``full``: as :func:`noise_model`'s."""
    from dotshell.runtime.parallel import bands, split_bands
    from dotshell_codings import kernels

    if stack.shape[0] < 4:
        return None
    full = full_scale(stack[0]) if full is None else full
    least, most = (np.float32(t) for t in _thresholds_of(full))
    top = int(full)  # w − b ≤ w ≤ top
    bounds = bands((stack.shape[1] + 1) // 2)  # the sampled rows
    per_band = np.zeros((len(bounds) - 1, top + 1), np.int64)
    split_bands(kernels.model_levels, bounds, stack, least, most, per_band)
    levels = per_band.sum(axis=0)
    n = int(levels.sum())
    if n < 100:
        return None
    # the bins' ends as np.array_split cuts n ranks: the first n % bins one longer
    ends = np.cumsum(n // _MODEL_BINS + (np.arange(_MODEL_BINS) < n % _MODEL_BINS))
    rank0 = np.cumsum(levels) - levels  # rank of each level's first pixel
    first_rank = rank0 + np.cumsum(per_band, axis=0) - per_band  # ... in each band
    width = min(2 * top, _MODEL_MAX_RESIDUAL) + 2  # beyond: the last
    counts = np.zeros((len(bounds) - 1, _MODEL_BINS, width), np.int32)
    split_bands(kernels.model_residuals, bounds, stack, least, most, first_rank, ends,
                _MODEL_PAIR_STRIDE, counts)
    below = np.cumsum(counts.sum(axis=0), axis=1)  # per bin: residuals up to each |r|
    total = below[:, -1]
    # per bin the two middle |r| (as searchsorted(side="right"): the sums ≤ the middle rank)
    r_mid = np.stack([(below <= k[:, None]).sum(axis=1) for k in ((total - 1) // 2, total // 2)],
                     axis=1)
    if (r_mid[:, 1] >= width - 1).any():
        return None
    ys = [float(y) / 0.4549 for y in np.median(r_mid.astype(np.float32) ** 2, axis=1)]
    # per bin the two middle ranks' levels, their median in float32 as np.median takes it
    starts = np.concatenate([[0], ends[:-1]])
    picks = np.stack([starts + (ends - starts - 1) // 2, starts + (ends - starts) // 2], axis=1)
    xs = np.median(np.searchsorted(rank0 + levels, picks, side="right").astype(np.float32),
                   axis=1)
    return _model_line([float(x) for x in xs], ys)
