"""dotshell.parallel: a pass split across threads covers its range once, errors reach the
caller, and a forked child (a process-based batch worker) gets a pool of its own."""

from __future__ import annotations

import os
import threading

import numpy as np
import pytest

from dotshell import parallel


def _mark(out: np.ndarray, seen: list, start: int, stop: int) -> None:
    out[start:stop] += 1
    seen.append(threading.get_ident())


def test_split_covers_the_range_once_on_several_threads():
    out = np.zeros(1000, np.int64)
    seen: list = []
    with parallel.threads(3):
        parallel.split(_mark, len(out), out, seen)
    assert (out == 1).all() and len(seen) == 3
    small = np.zeros(5, np.int64)
    parallel.split(_mark, len(small), small, [])  # below min_chunk: one range
    assert (small == 1).all()


def test_errors_of_a_range_reach_the_caller():
    def fail(start: int, stop: int) -> None:
        if start > 0:
            raise ValueError(f"range {start}-{stop}")

    with parallel.threads(2), pytest.raises(ValueError, match="range 500-1000"):
        parallel.split(fail, 1000)


def test_a_forked_child_splits_on_its_own_pool():
    out = np.zeros(100, np.int64)
    with parallel.threads(2):
        parallel.split(_mark, len(out), out, [])  # the parent's pool exists
        pid = os.fork()
        if pid == 0:
            child = np.zeros(100, np.int64)
            parallel.split(_mark, len(child), child, [])
            os._exit(0 if (child == 1).all() else 1)
    _, status = os.waitpid(pid, 0)
    assert os.WEXITSTATUS(status) == 0
