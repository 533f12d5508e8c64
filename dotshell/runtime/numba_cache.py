"""numba's on-disk cache of compiled kernels, made safe for processes that compile at once.

dotshell's kernels are compiled with ``cache=True``: the first process to call one compiles it
for the argument types of the call and writes it under ``__pycache__`` (an index per function,
``name-LINE.py311.nbi``, mapping each signature to a data file ``name-LINE.py311.N.nbc``); the
others load it. numba writes each file atomically but not the index and the data file
together: two processes compiling *different* signatures of one function at once both read
the index, both pick the same free data file number, and each writes its own index entry and
its own code under that number. The index keeps one entry, the data file the other's code, and
from then on every process that loads that signature runs machine code compiled for other
argument types — wrong results or a crash, kept in the cache until the source changes.
Measured with numba 0.68 on a toy kernel ``x * 2``: two processes compiling it for an int and
a float at once, and a third process then got ``4`` for ``2.5 * 2``.

It happens on a fresh install whenever two processes reach a kernel's first call with
different frame types at the same moment: a ``dotshell batch`` on Dask workers over runs of an
8-bit and a 12-bit camera, two scans started together, the test suite's workers.

:func:`install` makes each cache operation hold a lock on a file in the cache's directory
(``numba-cache.lock``, ``flock``): a write (index read, data file chosen, index and data
written) is exclusive, a read (index and data read) shared. Writes take milliseconds; loads run
in parallel. Where the lock file cannot be opened (a read-only ``__pycache__``: nothing is
written there either) the operation runs unlocked, as numba's own.
"""

from __future__ import annotations

import contextlib
import functools
import os
from collections.abc import Iterator

try:
    import fcntl
except ImportError:  # not POSIX: numba's cache as it is
    fcntl = None  # type: ignore[assignment]  # mypy's idiom for a module that may be missing

#: the lock file made in each cache directory
LOCK_NAME = "numba-cache.lock"


@contextlib.contextmanager
def cache_lock(cache_dir: str, exclusive: bool) -> Iterator[None]:
    """Hold the lock of the numba cache in ``cache_dir`` (shared or exclusive) for the block."""
    try:
        fd = os.open(os.path.join(cache_dir, LOCK_NAME), os.O_RDWR | os.O_CREAT, 0o666)
    except OSError:
        fd = -1
    try:
        if fd >= 0:
            fcntl.flock(fd, fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH)
        yield
    finally:
        if fd >= 0:
            os.close(fd)  # releases the lock


def install() -> None:
    """Lock numba's cache index and data files for every cached function of this process (once;
    called by the modules that define dotshell's kernels, before any is compiled)."""
    from numba.core.caching import IndexDataCacheFile

    if fcntl is None or getattr(IndexDataCacheFile, "dotshell_locked", False):
        return
    save, load = IndexDataCacheFile.save, IndexDataCacheFile.load

    @functools.wraps(save)
    def locked_save(self, key, data):
        with cache_lock(self._cache_path, exclusive=True):
            return save(self, key, data)

    @functools.wraps(load)
    def locked_load(self, key):
        with cache_lock(self._cache_path, exclusive=False):
            return load(self, key)

    # a deliberate patch of numba's class (methods wrapped in the cache lock)
    IndexDataCacheFile.save, IndexDataCacheFile.load = locked_save, locked_load  # type: ignore[method-assign]
    setattr(IndexDataCacheFile, "dotshell_locked", True)  # noqa: B010 (a mark numba does not declare)
