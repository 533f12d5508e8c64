"""Image-sized arrays on transparent huge pages (Linux), for the per-view maps of the decode
and the triangulation.

Why (measured, docs/performance.md): :mod:`dotshell.runtime` gives every allocation of 1 MiB
or more its own mapping, returned to the system when freed, so that a reconstruction's
resident memory does not grow view by view. The price was paid per view: every new map is
touched page by page, ~5 600 page faults (4 KiB each) per full-resolution view, 10-30 ms of
system time. numpy asks for huge pages only from 4 MiB up, and the kernel gives them only to
the 2 MiB-aligned stretches of a mapping. :func:`empty` aligns the array to 2 MiB and asks for
huge pages itself: one fault per 2 MiB. Where the kernel gives no huge pages (transparent
huge pages off, not Linux), the arrays are plain arrays on ordinary pages.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import math
from typing import Any, Callable

import numpy as np

HUGE_PAGE = 2 << 20  #: bytes of a transparent huge page (x86-64, aarch64 with 4 KiB pages)
MIN_BYTES = 1 << 20  #: smaller arrays are plain arrays (they would waste most of a huge page)
_MADV_HUGEPAGE = 14  # Linux <sys/mman.h>

@functools.cache
def _madvise() -> Callable[[int, int, int], int] | None:
    """The C library's ``madvise``, or None where there is none (not glibc/Linux)."""
    name = ctypes.util.find_library("c")
    try:
        fn: Any = ctypes.CDLL(name, use_errno=True).madvise if name else None
    except (OSError, AttributeError):
        return None
    if fn is not None:
        fn.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
        fn.restype = ctypes.c_int
    return fn


def empty(shape: int | tuple[int, ...], dtype: Any) -> np.ndarray:
    """An uninitialized C-contiguous array like :func:`numpy.empty`, placed on transparent
    huge pages when it is at least :data:`MIN_BYTES` (its memory rounded up to whole huge
    pages, at most 2 MiB more per array)."""
    dtype = np.dtype(dtype)
    dims = (shape,) if isinstance(shape, int) else tuple(shape)
    nbytes = math.prod(dims) * dtype.itemsize
    madvise = _madvise() if nbytes >= MIN_BYTES else None
    if madvise is None:
        return np.empty(dims, dtype)
    span = -(-nbytes // HUGE_PAGE) * HUGE_PAGE
    raw = np.empty(span + HUGE_PAGE, np.uint8)
    offset = -raw.ctypes.data % HUGE_PAGE
    madvise(raw.ctypes.data + offset, span, _MADV_HUGEPAGE)  # a refusal leaves ordinary pages
    return raw[offset:offset + nbytes].view(dtype).reshape(dims)


def zeros(shape: int | tuple[int, ...], dtype: Any) -> np.ndarray:
    """:func:`empty` filled with zeros."""
    out = empty(shape, dtype)
    out.fill(0)
    return out
