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

**Exit.** When the command's work is done, tearing the interpreter down (freeing every module
of numba's LLVM, VTK, scipy...) took 0.5-1.7 s of the demo's ``dotshell reconstruct`` on 2 cores.
:func:`exit_now` ends the process without it, once no thread of ours is still working.
"""

from __future__ import annotations

import atexit
import ctypes
import ctypes.util
import os
import sys
import threading

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
