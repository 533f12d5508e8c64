"""Image-sized arrays on transparent huge pages (Linux), lent from a pool, for the per-view
maps of the decode and the triangulation.

Why (measured, docs/performance.md): :mod:`dotshell.runtime.process` gives every allocation of 1 MiB
or more its own mapping, returned to the system when freed, so that a reconstruction's
resident memory does not grow view by view. The price was paid per view: every new map is
touched page by page, ~5 600 page faults (4 KiB each) per full-resolution view, 10-30 ms of
system time. numpy asks for huge pages only from 4 MiB up, and the kernel gives them only to
the 2 MiB-aligned stretches of a mapping. :func:`empty` aligns the array to 2 MiB and asks for
huge pages itself: one fault per 2 MiB. Where the kernel gives no huge pages (transparent
huge pages off, not Linux), the arrays are plain arrays on ordinary pages.

Even on huge pages the kernel zeroes every new page: a full view's ~70 MB of new maps cost
11-23 ms of system time per view (``clear_page_erms``, the largest single entry in a profile
of the view). So the memory is lent, not given: an array's block goes back to an idle pool
when the array and every view of it are gone, and the next array of that size takes it as it
is, already resident. The pool keeps at most :data:`MAX_IDLE_BYTES` idle (the least recently
returned blocks go back to the system first); :func:`release` gives all of it back (the
reconstruction calls it when its views are done).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import math
import os
import threading
from collections import OrderedDict
from typing import Any, Callable

import numpy as np

HUGE_PAGE = 2 << 20  #: bytes of a transparent huge page (x86-64, aarch64 with 4 KiB pages)
MIN_BYTES = 1 << 20  #: smaller arrays are plain arrays (they would waste most of a huge page)
MAX_IDLE_BYTES = 256 << 20  #: idle blocks kept for reuse (~3 full views' maps at 1280×1024)
#: a block up to this much larger than asked for is lent rather than a new one made
#: (the solves' outputs differ in size from view to view with the decoded pixels)
SLACK = 1.25
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


class _Pool:
    """Idle blocks (2 MiB-aligned stretches of numpy buffers), oldest returned first."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._idle: OrderedDict[int, tuple[np.ndarray, int]] = OrderedDict()  # id → (raw, span)
        self.idle_bytes = 0

    def take(self, span: int) -> np.ndarray | None:
        """The idle block closest in size of at least ``span`` bytes (at most :data:`SLACK`
        times it), taken out of the pool; None if there is none."""
        with self._lock:
            best = None
            for key, (_, size) in self._idle.items():
                if span <= size <= span * SLACK and (best is None or size < best[1]):
                    best = (key, size)
            if best is None:
                return None
            raw, size = self._idle.pop(best[0])
            self.idle_bytes -= size
            return raw

    def give_back(self, raw: np.ndarray, span: int) -> None:
        with self._lock:
            self._idle[id(raw)] = (raw, span)
            self.idle_bytes += span
            while self.idle_bytes > MAX_IDLE_BYTES:
                _, (_, size) = self._idle.popitem(last=False)
                self.idle_bytes -= size

    def clear(self) -> None:
        with self._lock:
            self._idle.clear()
            self.idle_bytes = 0


_POOL = _Pool()
os.register_at_fork(after_in_child=_POOL.clear)


class _Lease:
    """A block lent to one array: numpy makes it the base of the array and of every view
    of it, so it dies, giving the block back, when the last of them does."""

    __slots__ = ("__array_interface__", "_raw", "_span")

    def __init__(self, raw: np.ndarray, span: int, nbytes: int) -> None:
        self._raw, self._span = raw, span
        self.__array_interface__ = {"shape": (nbytes,), "typestr": "|u1", "version": 3,
                                    "data": (_aligned(raw), False)}

    def __del__(self) -> None:
        pool = _POOL  # None while the interpreter tears the module down
        if pool is not None:
            pool.give_back(self._raw, self._span)


def _aligned(raw: np.ndarray) -> int:
    """Address of the first huge page boundary in ``raw``."""
    return raw.ctypes.data + (-raw.ctypes.data % HUGE_PAGE)


def _new_block(span: int, madvise: Callable[[int, int, int], int]) -> np.ndarray:
    raw = np.empty(span + HUGE_PAGE, np.uint8)
    madvise(_aligned(raw), span, _MADV_HUGEPAGE)  # a refusal leaves ordinary pages
    return raw


def empty(shape: int | tuple[int, ...], dtype: Any) -> np.ndarray:
    """An uninitialized C-contiguous array like :func:`numpy.empty`, placed on transparent
    huge pages when it is at least :data:`MIN_BYTES` (its memory rounded up to whole huge
    pages, at most 2 MiB more per array), in a block from the idle pool when one fits (its
    contents are then whatever the last array there left)."""
    dtype = np.dtype(dtype)
    dims = (shape,) if isinstance(shape, int) else tuple(shape)
    nbytes = math.prod(dims) * dtype.itemsize
    madvise = _madvise() if nbytes >= MIN_BYTES else None
    if madvise is None:
        return np.empty(dims, dtype)
    span = -(-nbytes // HUGE_PAGE) * HUGE_PAGE
    raw = _POOL.take(span)
    if raw is None:
        raw = _new_block(span, madvise)
    else:
        span = raw.nbytes - HUGE_PAGE
    return np.asarray(_Lease(raw, span, nbytes)).view(dtype).reshape(dims)


def zeros(shape: int | tuple[int, ...], dtype: Any) -> np.ndarray:
    """:func:`empty` filled with zeros."""
    out = empty(shape, dtype)
    out.fill(0)
    return out


def idle_bytes() -> int:
    """Bytes of the idle blocks the pool holds."""
    return _POOL.idle_bytes


def release() -> None:
    """Give every idle block back to the system (arrays still in use keep theirs)."""
    _POOL.clear()
