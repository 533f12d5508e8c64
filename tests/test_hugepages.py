"""dotshell.runtime.hugepages: image-sized arrays aligned to huge pages, which the kernel backs with
one page fault per 2 MiB instead of one per 4 KiB where transparent huge pages are on."""

from __future__ import annotations

import resource
from pathlib import Path

import numpy as np
import pytest

from dotshell.runtime import hugepages


def _thp_mode() -> str:
    path = Path("/sys/kernel/mm/transparent_hugepage/enabled")
    text = path.read_text() if path.exists() else ""
    return text[text.find("[") + 1:text.find("]")] if "[" in text else "never"


def test_arrays_are_plain_arrays_of_the_asked_shape_and_type():
    for shape, dtype in [((1024, 1280), bool), ((2, 1024, 1280), np.int32), ((300_000, 3), float),
                         (10, np.uint8), ((0, 3), float)]:
        a = hugepages.empty(shape, dtype)
        assert a.shape == (shape if isinstance(shape, tuple) else (shape,))
        assert a.dtype == np.dtype(dtype) and a.flags.c_contiguous and a.flags.writeable
        a[...] = 1
        assert (a == 1).all()
    z = hugepages.zeros((1024, 1280), np.float32)
    assert z.shape == (1024, 1280) and not z.any()


def test_large_arrays_start_on_a_huge_page_small_ones_are_plain():
    big = hugepages.empty((1024, 1280), bool)  # 1.25 MiB
    assert big.ctypes.data % hugepages.HUGE_PAGE == 0
    small = hugepages.empty((100, 100), np.float32)
    assert small.base is None  # numpy's own allocation


@pytest.mark.skipif(_thp_mode() not in ("madvise", "always"),
                    reason="transparent huge pages are off on this machine")
def test_touching_image_sized_arrays_faults_once_per_2_mib():
    """16 boolean camera images (1.25 MiB each, below numpy's own 4 MiB huge page threshold):
    320 faults each on 4 KiB pages."""
    def faults_touching() -> int:
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        arrays = [hugepages.empty((1024, 1280), bool) for _ in range(16)]
        for a in arrays:
            a.fill(True)
        return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

    faults = min(faults_touching() for _ in range(3))
    assert faults < 16 * 320 // 4, f"{faults} page faults for 16 images on huge pages"


def _big() -> np.ndarray:
    return hugepages.empty((1024, 1280), np.float32)  # 5 MiB, a 6 MiB block


def test_a_freed_array_lends_its_memory_to_the_next_one_not_before():
    hugepages.release()
    a = _big()
    address = a.ctypes.data
    part = a[100:200]  # a view keeps the block lent
    del a
    assert hugepages.idle_bytes() == 0
    b = _big()
    assert b.ctypes.data != address
    del part
    assert hugepages.idle_bytes() == 6 << 20
    c = _big()
    assert c.ctypes.data == address and hugepages.idle_bytes() == 0
    del b, c
    hugepages.release()
    assert hugepages.idle_bytes() == 0


def test_a_slightly_larger_idle_block_is_lent_a_much_larger_one_is_not():
    hugepages.release()
    a = hugepages.empty((700_000, 3), np.float64)  # 16.02 MB: an 18 MiB block
    address = a.ctypes.data
    del a
    b = hugepages.empty((650_000, 3), np.float64)  # 15.6 MB: 16 MiB, 18 ≤ 1.25 × 16
    assert b.ctypes.data == address
    del b
    c = hugepages.empty((1024, 1280), bool)  # 1.25 MiB: 2 MiB, 18 MiB is far too large
    assert c.ctypes.data != address and hugepages.idle_bytes() == 18 << 20
    del c
    hugepages.release()


def test_reused_memory_is_zeroed_by_zeros_and_shared_by_nothing_alive():
    hugepages.release()
    a = _big()
    a.fill(7.0)
    del a
    z = hugepages.zeros((1024, 1280), np.float32)
    assert not z.any()
    keep = [_big() for _ in range(3)]
    for i, k in enumerate(keep):
        k.fill(i)
    assert [float(k.mean()) for k in keep] == [0.0, 1.0, 2.0]  # no two arrays share a block
    assert len({k.ctypes.data for k in keep + [z]}) == 4
    del keep, z
    hugepages.release()


def test_the_idle_pool_keeps_at_most_its_limit_giving_back_the_oldest(monkeypatch):
    hugepages.release()
    monkeypatch.setattr(hugepages, "MAX_IDLE_BYTES", 13 << 20)
    first, second, third = _big(), _big(), _big()
    address = first.ctypes.data
    del first, second, third  # 18 MiB idle > 13: the first freed goes back to the system
    assert hugepages.idle_bytes() == 12 << 20
    again = [_big() for _ in range(2)]
    assert address not in {a.ctypes.data for a in again}
    del again
    hugepages.release()


@pytest.mark.skipif(_thp_mode() not in ("madvise", "always"),
                    reason="transparent huge pages are off on this machine")
def test_reusing_a_freed_map_faults_no_page():
    hugepages.release()
    a = _big()
    a.fill(1.0)
    del a
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    b = _big()
    b.fill(2.0)
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
    assert faults < 3, f"{faults} page faults touching a reused map"
    del b
    hugepages.release()
