"""Process-wide settings of the ``dotshell`` command: BLAS on one thread, and large
allocations returned to the system when freed. Python callers of the pipeline can call
:func:`configure_process` (or either function) themselves; the benchmarks do, as the command
does.

**BLAS threads.** dotshell's dense products are small — (N, 3) points or rays times a 3×3
rotation, 3-vectors dotted — and numpy hands them to its BLAS (OpenBLAS), which splits each
across threads. On a busy machine, or once open3d's ray caster has run (its OpenMP threads stay
awake), the threads cost far more than they save (measured on 2 cores, docs/performance.md:
1.3 M points × 3×3 25 ms on one thread against 45-90 ms on two; a 30 000-long dot product
0.09 ms against 2.6 ms). Writing the products element by element is slower still (100 ms).

**Heap.** glibc serves an allocation from its heap unless it is larger than the mmap threshold,
which starts at 128 KiB and rises to the size of every large block freed (up to 32 MiB). After
the first full-size temporaries are freed, the next ones of a few MiB come from the heap, which
keeps the freed memory: a reconstruction's resident memory grows view by view. A fixed
threshold of 1 MiB keeps every image-sized array in its own mapping, returned when freed
(measured: ``dotshell reconstruct`` of the demo run, RSS between views 517 → 380 MiB).
A loop that allocates and frees the same few MiB many times pays for it in page faults: it
runs within :func:`heap_reused`.

**Exit.** When the command's work is done, tearing the interpreter down (freeing every module
of numba's LLVM, VTK, scipy...) took 0.5-1.7 s of the demo's ``dotshell reconstruct`` on 2 cores.
:func:`exit_now` ends the process without it, once no thread of ours is still working.
"""

from __future__ import annotations

import atexit
import ctypes
import ctypes.util
import functools
import os
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

from threadpoolctl import threadpool_limits

_M_MMAP_THRESHOLD = -3  # mallopt parameters (glibc malloc.h)
_M_TRIM_THRESHOLD = -1
_DEFAULT_TRIM_THRESHOLD = 128 * 1024  # glibc's, kept once the mmap threshold is fixed


def limit_blas_threads(threads: int = 1) -> None:
    """Limit the BLAS libraries loaded in this process (numpy's OpenBLAS) to ``threads``
    threads from now on."""
    threadpool_limits(threads, user_api="blas")


#: the threshold :func:`fix_mmap_threshold` set in this process (None: glibc's own, dynamic)
_fixed_threshold: int | None = None


def fix_mmap_threshold(nbytes: int = 1 << 20) -> bool:
    """Serve allocations of ``nbytes`` or more by their own mappings (glibc); False where the
    C library has no ``mallopt`` (not glibc) and nothing changed."""
    global _fixed_threshold
    libc = _libc()
    if libc is None or not libc.mallopt(_M_MMAP_THRESHOLD, nbytes):
        return False
    _fixed_threshold = nbytes
    return True


@contextmanager
def heap_reused(nbytes: int = 32 << 20) -> Iterator[None]:
    """Within the block, allocations below ``nbytes`` come from the heap, where a block freed
    is given to the next allocation; at its end the heap's free pages go back to the system
    (``malloc_trim``) and the threshold :func:`fix_mmap_threshold` set is restored. For a loop
    that allocates and frees the same few MiB many times: each mapping of its own is new
    pages the kernel must zero on first touch (the mesh step's thinning of 5.5 M points, 250 k
    at a time, took 190 k page faults, 0.4 s of system CPU, with the 1 MiB threshold). Does
    nothing in a process whose threshold was not fixed (glibc's own already reuses them)."""
    fixed = _fixed_threshold
    libc = _libc() if fixed is not None else None
    if libc is None or not libc.mallopt(_M_MMAP_THRESHOLD, nbytes):
        yield
        return
    libc.mallopt(_M_TRIM_THRESHOLD, 2 * nbytes)  # a freed block on top of the heap stays too
    try:
        yield
    finally:
        libc.mallopt(_M_TRIM_THRESHOLD, _DEFAULT_TRIM_THRESHOLD)
        libc.mallopt(_M_MMAP_THRESHOLD, fixed)
        libc.malloc_trim(0)


@functools.cache
def _libc() -> ctypes.CDLL | None:
    """The C library, if it is glibc (has ``mallopt`` and ``malloc_trim``)."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
        return libc if libc is not None and libc.mallopt and libc.malloc_trim else None
    except (OSError, AttributeError):
        return None


def configure_process() -> None:
    """Both settings, as the ``dotshell`` command runs."""
    limit_blas_threads(1)
    fix_mmap_threshold()


def exit_now(code: int) -> None:
    """End the process with exit status ``code`` without the interpreter's teardown — when
    every other thread is a daemon (the decode's idle pass threads are shut down first);
    otherwise return and let Python join the threads and exit as usual. The ``atexit``
    handlers still run (logging, other libraries') and stdout/stderr are flushed (status 120
    if that fails, as Python's own exit); the
    command's files are all written (atomically, synced) before it returns its status."""
    from dotshell.runtime.parallel import shutdown

    shutdown()
    main = threading.main_thread()
    if any(t is not main and not t.daemon and t.is_alive() for t in threading.enumerate()):
        return
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError, AttributeError):  # gone (a broken pipe): as Python does
            code = code or 120
    os._exit(code)
