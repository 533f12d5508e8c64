"""A plain numpy integer Gray-code decoder: the floor a decoder's speed is compared with.

Per axis, each bit is "pattern brighter than its inverse" (integer comparison of the camera's
own dtype), Gray bits turn into binary by a running XOR (MSB first), and a pixel is valid where
white − black reaches the shadow threshold and the code lands on the projector. No robust
classification, no sub-pixel refinement, no edge tolerance: it is what a decoder cannot be
faster than by much, not a decoder to scan with.

It is timed as a plain numpy program runs it: :func:`decode` runs within
:func:`dotshell.runtime.process.heap_reused`, glibc's default reuse of freed blocks for its
image-sized temporaries. In a process set up as the ``dotshell`` command sets itself up
(:func:`~dotshell.runtime.process.configure_process`: every block of 1 MiB or more in a
mapping of its own, returned when freed) each of its ~10 temporaries a call was a new mapping
touched page by page: 39-41 ms a call on the full-resolution bench view against 22-26 ms in a
plain process or within ``heap_reused`` (measured 2026-12-06, quiet host). Until then the
benchmarks timed it in the configured process, and the peer was 60-75 % slower than numpy is.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from dotshell.runtime.process import heap_reused
from dotshell_codings.graycode import code_bits, code_offset


@dataclass
class IntegerCodes:
    """Projector column and row (int32 pixels, centred code) and where both are valid."""

    column: np.ndarray
    row: np.ndarray
    valid: np.ndarray


def decode_axis(frames: Sequence[np.ndarray], names: list[str], prefix: str,
                size: int) -> tuple[np.ndarray, np.ndarray]:
    """Projector coordinate (int32) of one axis and where it lies on the projector."""
    n = code_bits(size)
    index = {name: i for i, name in enumerate(names)}
    code = np.zeros(frames[0].shape, np.int32)
    binary = np.zeros(frames[0].shape, bool)
    for i in range(n):
        gray = frames[index[f"{prefix}_{i:02d}"]] > frames[index[f"{prefix}_{i:02d}_inv"]]
        np.logical_xor(binary, gray, out=binary)
        code <<= 1
        code |= binary
    code -= code_offset(size)
    return code, (code >= 0) & (code < size)


def decode(frames: Sequence[np.ndarray], names: list[str], projector_size: tuple[int, int],
           shadow_dn: float) -> IntegerCodes:
    """Decode columns and rows; ``shadow_dn``: least white − black of a lit pixel (DN)."""
    with heap_reused():  # as a plain numpy program allocates (module docstring)
        return _decode(frames, names, projector_size, shadow_dn)


def _decode(frames: Sequence[np.ndarray], names: list[str], projector_size: tuple[int, int],
            shadow_dn: float) -> IntegerCodes:
    white = frames[names.index("white")].astype(np.int32)
    lit = (white - frames[names.index("black")]) >= shadow_dn
    column, col_ok = decode_axis(frames, names, "col", projector_size[0])
    row, row_ok = decode_axis(frames, names, "row", projector_size[1])
    return IntegerCodes(column, row, lit & col_ok & row_ok)
