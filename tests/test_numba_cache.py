"""dotshell.runtime.numba_cache: two processes compiling different signatures of one cached kernel at
the same moment leave a cache that gives every later process the right code for each."""

import subprocess
import sys

import pytest

pytest.importorskip("fcntl")

KERNEL = "import numba\n\n\n@numba.njit(cache=True)\ndef twice(x):\n    return x * 2\n"

#: a process's first call of ``twice(value)``, run as ``child.py DIR VALUE LATE``: it meets the
#: other process (a marker file each, waited for up to 1 s) after reading the kernel's cache
#: index and before writing it, which is numba's race unless the lock keeps the other process
#: out (then the wait times out); LATE=1 writes its compiled code last. Exits 1 if wrong.
CHILD = """
import os, sys, time
from pathlib import Path
from numba.core import caching
from dotshell.runtime import numba_cache

numba_cache.install()
here, value, late = Path(sys.argv[1]), eval(sys.argv[2]), sys.argv[3] == "1"
cache_file = caching.IndexDataCacheFile
save_index, save_data = cache_file._save_index, cache_file._save_data

def meet_then_save_index(self, overloads):
    (here / f"at-index-{os.getpid()}").touch()
    end = time.monotonic() + 1.0
    while len(list(here.glob("at-index-*"))) < 2 and time.monotonic() < end:
        time.sleep(0.01)
    return save_index(self, overloads)

def save_data_late(self, name, data):
    time.sleep(0.5 if late else 0.0)
    return save_data(self, name, data)

cache_file._save_index = meet_then_save_index
cache_file._save_data = save_data_late
sys.path.insert(0, str(here))
import toy_kernel
sys.exit(0 if toy_kernel.twice(value) == value * 2 else 1)
"""


def test_signatures_compiled_at_once_are_each_loaded_with_their_own_code(tmp_path):
    """numba alone (0.68, checked by hand): the cache ends with one index entry, which may
    point at the other signature's code (a new process then computed 2.5 × 2 = 4)."""
    (tmp_path / "toy_kernel.py").write_text(KERNEL)
    (tmp_path / "child.py").write_text(CHILD)
    procs = [subprocess.Popen([sys.executable, str(tmp_path / "child.py"), str(tmp_path),
                               value, late]) for value, late in (("3", "1"), ("2.5", "0"))]
    assert [p.wait(120) for p in procs] == [0, 0]
    check = (f"import sys; sys.path.insert(0, {str(tmp_path)!r}); import toy_kernel as k; "
             "print(k.twice(3), k.twice(2.5), len(k.twice.stats.cache_hits))")
    out = subprocess.run([sys.executable, "-c", check], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["6", "5.0", "2"]  # both loaded from the cache, both right
