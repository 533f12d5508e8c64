"""dotshell.hugepages: image-sized arrays aligned to huge pages, which the kernel backs with
one page fault per 2 MiB instead of one per 4 KiB where transparent huge pages are on."""

from __future__ import annotations

import resource
from pathlib import Path

import numpy as np
import pytest

from dotshell import hugepages


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
