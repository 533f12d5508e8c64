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
"""

from __future__ import annotations

import ctypes
import ctypes.util

from threadpoolctl import threadpool_limits

_M_MMAP_THRESHOLD = -3  # mallopt parameter (glibc malloc.h)


def limit_blas_threads(threads: int = 1) -> None:
    """Limit the BLAS libraries loaded in this process (numpy's OpenBLAS) to ``threads``
    threads from now on."""
    threadpool_limits(threads, user_api="blas")


def fix_mmap_threshold(nbytes: int = 1 << 20) -> bool:
    """Serve allocations of ``nbytes`` or more by their own mappings (glibc); False where the
    C library has no ``mallopt`` (not glibc) and nothing changed."""
    name = ctypes.util.find_library("c")
    try:
        mallopt = ctypes.CDLL(name).mallopt if name else None
    except (OSError, AttributeError):
        return False
    return bool(mallopt and mallopt(_M_MMAP_THRESHOLD, nbytes))


def configure_process() -> None:
    """Both settings, as the ``dotshell`` command runs."""
    limit_blas_threads(1)
    fix_mmap_threshold()
