"""The compiled pass behind :mod:`dotshell.pipeline.decode_quality`: the steps between adjacent
decoded pixels of a projector coordinate map, counted along both image axes in one pass over
the rows (cut into bands across the cores, :mod:`dotshell.runtime.parallel`)."""

from __future__ import annotations

import numba
import numpy as np

from dotshell.runtime import numba_cache
from dotshell.runtime.parallel import bands, split_bands

numba_cache.install()  # cache files safe for processes compiling at once

#: Steps are summed in integers of 1/STEP_SCALE projector px (exact, the same in any order).
STEP_SCALE = 256.0


def step_counts(coord: np.ndarray, valid: np.ndarray, threshold_px: float) -> np.ndarray:
    """(2, 4) int64: per image axis (0 = along x, 1 = along y) the adjacent valid pairs, their
    summed step in 1/:data:`STEP_SCALE` projector px, the steps up and the steps back by more
    than ``threshold_px`` (projector px) — one pass over the rows, cut into bands across the
    cores."""
    coord = np.ascontiguousarray(coord, np.float32)
    valid = np.ascontiguousarray(valid, np.bool_)
    if coord.shape != valid.shape or coord.ndim != 2:
        raise ValueError(f"map {coord.shape} and mask {valid.shape} must be the same 2-D shape")
    bounds = bands(coord.shape[0], min_chunk=64)
    per_band = np.zeros((len(bounds) - 1, 2, 4), np.int64)
    split_bands(_count_steps, bounds, coord, valid, float(threshold_px), STEP_SCALE, per_band)
    return per_band.sum(axis=0)


@numba.njit(nogil=True, cache=True, inline="always")
def _tally(a, b, ok, threshold, scale):
    """One neighbour pair (a → b): (pair, step in 1/scale px, up, back); all 0 unless ``ok``.
    The step goes through int32 (it is below 2^31 / scale = 2^23 projector px; a float32 to
    int32 conversion vectorizes where one to int64 may not)."""
    d = b - a if ok else np.float32(0.0)
    return (np.int64(ok), np.int64(np.int32(d * scale)), np.int64(d > threshold),
            np.int64(d < -threshold))


@numba.njit(nogil=True, cache=True)
def _count_steps(coord, valid, threshold, scale, out, band, start, stop):
    """Rows ``start`` to ``stop`` of :func:`step_counts`: each pixel with its right and its
    lower neighbour (the lower one may lie in the next band: only read). Branch-free over a
    row, so the compiler can vectorize it."""
    h, w = coord.shape
    thr = np.float32(threshold)
    sc = np.float32(scale)
    nx = sx = ux = dx = np.int64(0)
    ny = sy = uy = dy = np.int64(0)
    for i in range(start, stop):
        c, v = coord[i], valid[i]
        for j in range(w - 1):
            p, s, u, d = _tally(c[j], c[j + 1], v[j] & v[j + 1], thr, sc)
            nx += p
            sx += s
            ux += u
            dx += d
        if i + 1 < h:
            c2, v2 = coord[i + 1], valid[i + 1]
            for j in range(w):
                p, s, u, d = _tally(c[j], c2[j], v[j] & v2[j], thr, sc)
                ny += p
                sy += s
                uy += u
                dy += d
    out[band, 0, 0], out[band, 0, 1], out[band, 0, 2], out[band, 0, 3] = nx, sx, ux, dx
    out[band, 1, 0], out[band, 1, 1], out[band, 1, 2], out[band, 1, 3] = ny, sy, uy, dy
