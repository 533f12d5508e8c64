"""A minimal reader of uncompressed, single-channel TIFF pages — the frame stacks
:class:`dotshell.run.frames.TiffFrameStore` writes — at the speed of the reads themselves.

A general TIFF library parses every tag of every page (~1 ms a page, 40-60 ms for a view of 42
frames on a busy 2-core machine); reading a view must cost little more than copying its bytes.
This walks the chain of image file directories (classic TIFF or BigTIFF, either byte order),
decodes only the tags a frame needs, and reads each page's strips straight into the caller's
array. Anything else (compression, several samples per pixel, a float or signed format, a
bit depth other than 8 or 16) is refused with a clear error. A file cut short (a crash while a
frame was written) yields the pages that are complete.
"""

from __future__ import annotations

import io
import struct
from dataclasses import dataclass
from typing import BinaryIO

import numpy as np

_WIDTH, _HEIGHT, _BITS, _COMPRESSION, _DESCRIPTION = 256, 257, 258, 259, 270
_STRIP_OFFSETS, _SAMPLES, _STRIP_BYTES, _SAMPLE_FORMAT = 273, 277, 279, 339
_WANTED = {_WIDTH, _HEIGHT, _BITS, _COMPRESSION, _DESCRIPTION, _STRIP_OFFSETS, _SAMPLES,
           _STRIP_BYTES, _SAMPLE_FORMAT}
# TIFF field type -> struct code (BYTE, ASCII, SHORT, LONG, IFD, LONG8, IFD8)
_TYPES = {1: "B", 2: "B", 3: "H", 4: "I", 13: "I", 16: "Q", 18: "Q"}


class TiffPageError(ValueError):
    """The file is not a TIFF of uncompressed 8/16-bit single-channel pages."""


@dataclass(frozen=True)
class Page:
    """One image of the file: where its pixel bytes are and what they are."""

    description: str
    shape: tuple[int, int]
    dtype: np.dtype
    strips: tuple[tuple[int, int], ...]  # (file offset, byte count) in row order


class _Layout:
    """Byte order and classic/BigTIFF field sizes of a file."""

    def __init__(self, head: bytes) -> None:
        order = {b"II": "<", b"MM": ">"}.get(head[:2])
        if order is None or len(head) < 8:
            raise TiffPageError("not a TIFF file (no II/MM byte-order mark)")
        magic = struct.unpack(order + "H", head[2:4])[0]
        if magic not in (42, 43):
            raise TiffPageError(f"not a TIFF file (version {magic})")
        self.big = magic == 43
        self.order = order
        # struct codes: entries in a directory, values in an entry, a file offset
        self.count, self.values, self.offset = ("Q", "Q", "Q") if self.big else ("H", "I", "I")
        self.entry = 20 if self.big else 12
        self.inline = 8 if self.big else 4
        self.first = struct.unpack(order + self.offset, head[8:16] if self.big else head[4:8])[0]


def read_pages(f: BinaryIO, size: int, stop_after: int | None = None) -> list[Page]:
    """The complete pages of the open file ``f`` of ``size`` bytes, in file order (at most
    ``stop_after``)."""
    if size < 8:
        return []  # created, header not written yet: no complete page
    lay = _Layout(f.read(16))
    pages: list[Page] = []
    offset, seen = lay.first, set()
    while offset and offset not in seen and (stop_after is None or len(pages) < stop_after):
        seen.add(offset)
        tags, offset = _read_ifd(f, lay, offset, size)
        if tags is None:
            break  # a directory cut short
        page = _page(tags, len(pages), lay.order)
        if any(o + n > size for o, n in page.strips):
            break  # pixel data cut short
        pages.append(page)
    return pages


def _read_ifd(f: BinaryIO, lay: _Layout, offset: int, size: int
              ) -> tuple[dict[int, tuple | bytes] | None, int]:
    csize = struct.calcsize(lay.count)
    if offset + csize > size:
        return None, 0
    f.seek(offset)
    n = struct.unpack(lay.order + lay.count, f.read(csize))[0]
    if n == 0:  # linked but not written yet (a writer appending it): no directory is empty
        return None, 0
    body = f.read(n * lay.entry + struct.calcsize(lay.offset))
    if len(body) < n * lay.entry + struct.calcsize(lay.offset):
        return None, 0
    tags: dict[int, tuple | bytes] = {}
    for i in range(n):
        e = body[i * lay.entry:(i + 1) * lay.entry]
        code, typ = struct.unpack(lay.order + "HH", e[:4])
        if code not in _WANTED or typ not in _TYPES:
            continue
        count = struct.unpack(lay.order + lay.values, e[4:lay.entry - lay.inline])[0]
        nbytes = count * struct.calcsize(_TYPES[typ])
        raw = e[lay.entry - lay.inline:][:nbytes]
        if nbytes > lay.inline:
            at = struct.unpack(lay.order + lay.offset, e[lay.entry - lay.inline:])[0]
            if at + nbytes > size:
                return None, 0
            here = f.tell()
            f.seek(at)
            raw = f.read(nbytes)
            f.seek(here)
        tags[code] = raw if typ == 2 else struct.unpack(f"{lay.order}{count}{_TYPES[typ]}", raw)
    nxt = struct.unpack(lay.order + lay.offset, body[n * lay.entry:])[0]
    return tags, nxt


def _page(tags: dict[int, tuple | bytes], index: int, order: str) -> Page:
    def one(code: int, default: int | None = None) -> int:
        if code not in tags:
            if default is None:
                raise TiffPageError(f"page {index} lacks TIFF tag {code}")
            return default
        return int(tags[code][0])

    bits, fmt = one(_BITS), one(_SAMPLE_FORMAT, 1)
    if one(_COMPRESSION, 1) != 1 or one(_SAMPLES, 1) != 1 or fmt != 1 or bits not in (8, 16):
        raise TiffPageError(f"page {index} is not an uncompressed 8/16-bit unsigned "
                            "single-channel image")
    offsets, counts = tags.get(_STRIP_OFFSETS, ()), tags.get(_STRIP_BYTES, ())
    shape = (one(_HEIGHT), one(_WIDTH))
    dtype = np.dtype(np.uint8 if bits == 8 else np.uint16).newbyteorder("<" if order == "<" else ">")
    if len(offsets) != len(counts) or sum(counts) != shape[0] * shape[1] * dtype.itemsize:
        raise TiffPageError(f"page {index}: its strips do not hold a {shape[1]}x{shape[0]} "
                            f"{bits}-bit image")
    raw = tags.get(_DESCRIPTION, b"")
    description = bytes(raw).split(b"\0", 1)[0].decode("utf-8", "replace")
    return Page(description, shape, dtype, tuple(zip(offsets, counts)))


def read_into(f: io.RawIOBase, page: Page, out: np.ndarray) -> None:
    """Read ``page``'s pixels into ``out`` (C-contiguous, ``page.shape``, native uint8/16,
    byte-swapped from a file of the other byte order)."""
    view = out.reshape(-1).view(np.uint8).data
    at = 0
    for offset, count in page.strips:
        f.seek(offset)
        if f.readinto(view[at:at + count]) != count:
            raise TiffPageError(f"the file ends inside page data at byte {offset}")
        at += count
    if not page.dtype.isnative:
        out.byteswap(inplace=True)
