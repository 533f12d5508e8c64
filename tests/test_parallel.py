"""dotshell.runtime.parallel: a pass split across threads covers its range once, errors reach the
caller, and a forked child (a process-based batch worker) gets a pool of its own."""

from __future__ import annotations

import os
import threading

import numpy as np
import pytest

from dotshell.runtime import parallel


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


def test_balanced_bands_cut_equal_cost_not_equal_length():
    cost = np.r_[np.full(600, 1.0), np.full(400, 10.0)]  # the lower rows hold most of the work
    with parallel.threads(2):
        bounds = parallel.balanced_bands(cost)
        assert parallel.bands(len(cost)) == [0, 500, 1000]
    assert bounds[0] == 0 and bounds[-1] == len(cost) and len(bounds) == 3
    halves = [cost[a:b].sum() for a, b in zip(bounds, bounds[1:])]
    assert abs(halves[0] - halves[1]) <= 10.0  # within one row's cost
    with parallel.threads(2):
        assert parallel.balanced_bands(np.zeros(0)) == [0]
        assert len(parallel.balanced_bands(cost, per_worker=4)) == 9


def test_a_thread_that_finishes_early_takes_the_ranges_left():
    """Ranges are taken one at a time: while one range is held up (waiting here for all the
    others), the other thread runs every other range; cut once per thread, it would wait for
    the held-up thread's share and the wait would time out."""
    n = 8
    done = np.zeros(n, np.int64)
    others_done = threading.Event()
    lock = threading.Lock()

    def work(band: int, start: int, stop: int) -> None:
        if band == 0:
            assert others_done.wait(timeout=20), "the other ranges were left to this thread"
        with lock:
            done[band] += 1
            if done[1:].sum() == n - 1:
                others_done.set()

    with parallel.threads(2):
        bounds = parallel.bands(800, per_worker=4)
        assert len(bounds) == n + 1
        parallel.split_bands(work, bounds)
    assert (done == 1).all()



def _joins(threads: int) -> tuple[list[int], list[int]]:
    """split_bands_joined on ``threads`` threads: (the bounds, the joins in the order made);
    each join asserts that the ranges up to it were done."""
    with parallel.threads(threads):
        bounds = parallel.bands(1200, per_worker=6)
    finished = np.zeros(len(bounds) - 1, bool)
    joined: list[int] = []
    lock = threading.Lock()

    def work(band: int, start: int, stop: int) -> None:
        with lock:
            finished[band] = True

    def join(i: int) -> None:
        with lock:
            assert finished[:i + 1].all(), f"join {i} before its ranges were done"
            joined.append(i)

    with parallel.threads(threads):
        parallel.split_bands_joined(work, bounds, join)
    return bounds, joined


def test_joins_run_in_order_once_the_ranges_up_to_each_are_done():
    """split_bands_joined: join(i) once for every range i >= 1, in order, each only after
    ranges 0 ... i; on one thread after all of them."""
    for threads in (1, 2, 3):
        bounds, joined = _joins(threads)
        assert joined == list(range(1, len(bounds) - 1))


def test_joins_do_not_wait_for_the_last_range():
    """The last range waits here until join(1) has run: the other thread makes the joins that
    are due as it finishes its ranges. Joined only after every range (as before), the wait
    would time out."""
    n = 8
    joined = threading.Event()

    def work(band: int, start: int, stop: int) -> None:
        if band == n - 1:
            assert joined.wait(timeout=20), "join(1) waited for the last range"

    def join(i: int) -> None:
        if i == 1:
            joined.set()

    with parallel.threads(2):
        bounds = parallel.bands(800, per_worker=4)
        assert len(bounds) == n + 1
        parallel.split_bands_joined(work, bounds, join)
    assert joined.is_set()
