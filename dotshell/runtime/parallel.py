"""Work split across the cores: compiled loops (numba, ``nogil``) run on index ranges in a pool
of Python threads, a thread per core taking the ranges one at a time (a pass may cut its range
into more ranges than cores, or by cost, :func:`balanced_bands`, so that no core waits for
another at its end).

Why threads and not numba's ``parallel=True`` (measured, docs/performance.md): the compiled
passes of a view are each a few milliseconds, and on a shared machine numba's OpenMP layer
made them 3-4x slower on two threads than on one (idle threads spin on the busy cores); the
passive wait policy cured that, but ``parallel=True`` also made each kernel take 4-12 s to
compile instead of under 1 s (a cold cache cost the test suite ~40 s per frame type). Plain
serial kernels that release the GIL, split by rows here, compile fast, wait without spinning,
and are safe to call from several threads at once.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Any, Callable, Iterator, Sequence

_POOL: ThreadPoolExecutor | None = None
_LIMIT: int | None = None
#: the machine's cores, read once: ``os.cpu_count()`` reads ``/sys`` at every call (8-40 µs
#: measured on the 2-core host, ~30 calls in a view's decode and triangulation)
_CORES = os.cpu_count() or 1


def workers() -> int:
    """Threads a pass is split across: ``DOTSHELL_THREADS`` if set, else ``OMP_NUM_THREADS``
    (as ``make test`` sets for its worker processes), else the cores."""
    if _LIMIT is not None:
        return _LIMIT
    for name in ("DOTSHELL_THREADS", "OMP_NUM_THREADS"):
        value = os.environ.get(name, "").strip()
        if value.isdigit() and int(value) > 0:
            return int(value)
    return _CORES


@contextmanager
def threads(n: int) -> Iterator[None]:
    """Split passes across at most ``n`` threads inside the block (benchmarks)."""
    global _LIMIT
    before, _LIMIT = _LIMIT, max(1, int(n))
    try:
        yield
    finally:
        _LIMIT = before


def _forget_pool() -> None:
    """In a forked child the parent's pool threads do not exist: start a new pool there."""
    global _POOL
    _POOL = None


os.register_at_fork(after_in_child=_forget_pool)


def _pool() -> ThreadPoolExecutor:
    global _POOL
    if _POOL is None:
        _POOL = ThreadPoolExecutor(max_workers=max(1, _CORES - 1),
                                   thread_name_prefix="dotshell-pass")
    return _POOL


def shutdown() -> None:
    """Stop the pool's threads (idle between passes); a later pass starts a new pool."""
    global _POOL
    pool, _POOL = _POOL, None
    if pool is not None:
        pool.shutdown(wait=True)


def _parts(per_worker: int) -> int:
    """Ranges to cut a pass into: ``per_worker`` per worker, one on one worker."""
    cores = workers()
    return cores * max(per_worker, 1) if cores > 1 else 1


def bands(n: int, min_chunk: int = 16, per_worker: int = 1) -> list[int]:
    """Bounds of the contiguous ranges :func:`split` cuts ``range(n)`` into: ``per_worker``
    per worker (one in all on one worker, where nothing is to balance), each of at least
    ``min_chunk`` (range i is ``bounds[i]`` to ``bounds[i + 1]``)."""
    parts = max(1, min(_parts(per_worker), n // max(min_chunk, 1)))
    return [n * i // parts for i in range(parts + 1)]


def balanced_bands(cost: Sequence[float], per_worker: int = 1) -> list[int]:
    """Bounds cutting ``range(len(cost))`` into ``per_worker`` ranges per worker of about
    equal summed ``cost`` (e.g. the decoded pixels of each image row), instead of equal
    length: a view's lit pixels are rarely spread evenly over its rows."""
    import numpy as np

    n = len(cost)
    parts = max(1, min(_parts(per_worker), n))
    total = np.concatenate([[0.0], np.cumsum(np.asarray(cost, np.float64))])
    cuts = np.searchsorted(total, total[-1] * np.arange(1, parts) / parts, side="left")
    return sorted({0, n, *(int(c) for c in cuts if 0 < c < n)})


def split(kernel: Callable[..., Any], n: int, *args: Any, min_chunk: int = 16,
          bounds: list[int] | None = None) -> None:
    """Run ``kernel(*args, start, stop)`` over ``range(n)`` cut into one contiguous range per
    worker (:func:`bands`, or the given ``bounds``); returns when all are done, re-raising the
    first error. The kernel must release the GIL (``nogil=True``) to run in parallel."""
    _run(kernel, bands(n, min_chunk) if bounds is None else bounds, args, False)


def split_bands(kernel: Callable[..., Any], bounds: list[int], *args: Any) -> None:
    """Run ``kernel(*args, i, bounds[i], bounds[i + 1])`` for every range i of ``bounds``
    (:func:`bands`), in parallel as :func:`split` does: for kernels that keep per-range
    state (indexed by i) for a serial pass that joins the ranges afterwards."""
    _run(kernel, bounds, args, True)


def split_bands_joined(kernel: Callable[..., Any], bounds: list[int], join: Callable[[int], Any],
                       *args: Any) -> None:
    """:func:`split_bands`, then ``join(i)`` for every range i ≥ 1 in order, each as soon as
    ranges 0 … i are done (by the thread that finished the last of them, while the other
    threads go on with later ranges; what is left when the last range is done, after it).
    For kernels whose ranges are joined in order afterwards (a scan that crosses the ranges'
    borders): the joins need not wait for the last range. ``join(i)`` may only touch what
    ranges 0 … i wrote (ranges after i run beside it)."""
    _run(kernel, bounds, args, True, join)


def _run(kernel: Callable[..., Any], bounds: list[int], args: tuple, numbered: bool,
         join: Callable[[int], Any] | None = None) -> None:
    """The ranges of ``bounds`` on at most :func:`workers` threads (the caller's and the
    pool's), each thread taking the next range not yet taken until none is left: with more
    ranges than threads, a thread that finishes early (less work in its rows, or a core less
    busy) takes over the rest. ``join``: see :func:`split_bands_joined`."""
    def call(i: int) -> Any:
        extra = (i, bounds[i], bounds[i + 1]) if numbered else (bounds[i], bounds[i + 1])
        return kernel(*args, *extra)

    n = len(bounds) - 1
    joins = _Joins(n, join)
    threads = min(n, workers(), _CORES)
    if threads <= 1:
        for i in range(n):
            call(i)
        joins.finish()
        return
    ranges = iter(range(n))
    lock = threading.Lock()

    def drain() -> None:
        while True:
            with lock:
                i = next(ranges, None)
            if i is None:
                return
            call(i)
            joins.done(i)

    futures = [_pool().submit(drain) for _ in range(threads - 1)]
    try:
        drain()  # the calling thread takes ranges too
    finally:
        for f in futures:
            f.result()
    joins.finish()


class _Joins:
    """The joins of :func:`split_bands_joined`: ``join(i)`` once ranges 0 … i are done, in
    order, one thread at a time (a thread that finds another joining goes back to its
    ranges; the last joins are made by :meth:`finish`)."""

    def __init__(self, n: int, join: Callable[[int], Any] | None) -> None:
        self.join, self.n = join, n
        self.finished = [False] * n
        self.next = 1  # the next range to join
        self.lock = threading.Lock()  # finished and next
        self.joining = threading.Lock()  # held by the thread making joins

    def done(self, i: int) -> None:
        """Range i is done: make the joins that are due, unless another thread is."""
        if self.join is None:
            return
        with self.lock:
            self.finished[i] = True
        if self.joining.acquire(blocking=False):
            try:
                self._due()
            finally:
                self.joining.release()

    def _due(self) -> None:
        join = self.join
        assert join is not None  # done() and finish() return at once without joins
        while True:
            with self.lock:
                i = self.next
                if i >= self.n or not all(self.finished[:i + 1]):
                    return
                self.next = i + 1
            join(i)

    def finish(self) -> None:
        """Every range is done: the joins not made yet, in order."""
        if self.join is None:
            return
        with self.joining:
            with self.lock:
                self.finished = [True] * self.n
            self._due()
