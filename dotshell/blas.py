"""BLAS threads: one per process for dotshell's work.

dotshell's dense products are small — (N, 3) points or rays times a 3×3 rotation, 3-vectors
dotted — and numpy hands them to its BLAS (OpenBLAS), which splits each across threads. On a
busy machine, or once open3d's ray caster has run (its OpenMP threads stay awake), the threads
cost far more than they save (measured on 2 cores, docs/performance.md: 1.3 M points × 3×3
25 ms on one thread against 45-90 ms on two; a 30 000-long dot product 0.09 ms against
2.6 ms). Writing the products element by element is slower still (100 ms), so the ``dotshell``
command runs BLAS on one thread; Python callers of the pipeline can call
:func:`limit_blas_threads` themselves.
"""

from __future__ import annotations

from threadpoolctl import threadpool_limits


def limit_blas_threads(threads: int = 1) -> None:
    """Limit the BLAS libraries loaded in this process (numpy's OpenBLAS) to ``threads``
    threads from now on."""
    threadpool_limits(threads, user_api="blas")
