"""Frame storage: the captured fringe frames of one view, written as they arrive and read back at
memory speed.

A run records its frame format in ``manifest.json`` (``frame_format``); each format is a
:class:`FrameStore` subclass handling one view:

* ``tiff-stack/1`` (:class:`TiffFrameStore`, what scans write): ``frames/view_NNN.tif``, one
  uncompressed multi-page TIFF per view, one page per frame in capture order, 8 or 16 bit as the
  camera delivers, each page's ImageDescription the frame's name. Every page is written with its
  own directory entry as the frame arrives, so a file cut short by a crash still reads up to its
  last complete page; the file is synced to the disk once per view (:meth:`FrameStore.close`).
  ImageJ/Fiji, tifffile and libtiff open it as an image stack; a Dask worker reads one view
  without touching the rest of the run. tifffile writes it; :mod:`dotshell.run.tiffpages` reads it
  (straight into the output array, without a general TIFF parser's per-page cost).
* ``png/1`` (:class:`PngFrameStore`, runs written before the TIFF stacks; read-only):
  ``frames/view_NNN/III_NAME.png``, one lossless PNG per frame. A run without ``frame_format``
  is of this format.

Why uncompressed TIFF (measured on a view of the simulated metal cylinder, 42 frames of
1280×1024 uint16, 110 MB, 2 cores at load 3-5; docs/performance.md has the table): it writes in
~50 ms and reads in ~50-70 ms per view, against 2.8-3.8 s and 1.1 s for PNG level 1; blosc/zstd or lz4 chunks in
zarr halve the size (42-55 %) but take 0.3-0.6 s to read and 1-2 s to write on 2 cores.
:func:`export_png` writes the PNG layout for people who want to look at single frames.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import BinaryIO, Callable, ClassVar, Sequence

import cv2
import numpy as np
import tifffile

from dotshell.run import tiffpages
from dotshell.errors import FrameError, RunError
from dotshell.run.framecheck import FrameSpec, dtype_for
from dotshell.run.lost import is_lost
from dotshell.run.layout import RunLayout

TIFF_STACK = "tiff-stack/1"
PNG_FILES = "png/1"
#: the format new runs are written in
CURRENT_FORMAT = TIFF_STACK

_TIFF_LIMIT_BYTES = 2**32 - 2**26  # past this a classic TIFF's 32-bit offsets overflow: BigTIFF


def check_image(image: np.ndarray, label: str) -> None:
    """Raise :class:`RunError` unless ``image`` is a 2-D uint8 or uint16 array (``label`` names
    it)."""
    if not isinstance(image, np.ndarray) or image.dtype not in (np.uint8, np.uint16) \
            or image.ndim != 2:
        what = f"{image.dtype} {image.shape}" if isinstance(image, np.ndarray) else \
            type(image).__name__
        raise RunError(f"{label} is {what}; cameras must return 2-D uint8 or uint16 images.")


def fsync_path(path: Path) -> None:
    """Flush a file or directory's data to the disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class FrameStore:
    """The stored frames of one view of a run, in capture order.

    ``names`` is the run's frame sequence (``manifest["frame_names"]``). Subclasses set
    ``format_id`` and implement the reading methods; a writable format also implements
    :meth:`append`, :meth:`sync` and :meth:`close`.
    """

    format_id: ClassVar[str] = ""

    def __init__(self, root: Path, view: int, names: Sequence[str]) -> None:
        self.root = Path(root)
        self.view = view
        self.names = list(names)

    @property
    def path(self) -> Path:
        """Where this view's frames are (a file or a directory)."""
        raise NotImplementedError

    def count(self) -> int:
        """How many frames of the view are on disk."""
        raise NotImplementedError

    def read_one(self, index: int) -> np.ndarray:
        """Frame ``index`` of the sequence, as captured."""
        raise NotImplementedError

    def read_all(self, spec: FrameSpec | None = None, fix: str = "",
                 out: np.ndarray | None = None) -> np.ndarray:
        """All frames of the view, (frames, height, width) in capture order, as captured. With
        a ``spec`` every frame is checked against it (:class:`~dotshell.errors.FrameError`
        naming the frame, then ``fix``); without, frames must agree with the first. ``out``:
        an array to read into when it has the stack's shape and type (the previous view's,
        once its frames are no longer needed: a fresh 110 MB array costs 20-50 ms of page
        faults); otherwise a new one is returned."""
        raise NotImplementedError

    def _refuse(self, frame: np.ndarray, label: str, expect: np.ndarray | None,
                spec: FrameSpec | None, fix: str) -> None:
        """Raise for a frame that is not like ``expect`` (the first frame) or ``spec``."""
        if spec is not None:
            spec.check(frame, label, fix)
        elif expect is not None and (frame.shape != expect.shape or frame.dtype != expect.dtype):
            raise FrameError(f"{label} is {frame.dtype} {frame.shape} where the view's first "
                             f"frame is {expect.dtype} {expect.shape}; a view is captured by "
                             f"one camera setting. {fix}".rstrip())

    def _check_values(self, out: np.ndarray, spec: FrameSpec | None, fix: str,
                      label: Callable[[int], str], peak: int | None = None) -> None:
        """Refuse values past the spec's bit depth (naming the frame): one pass over the stack
        for its largest value, unless the reader gives it (``peak``)."""
        if spec is None or not out.size or spec.bit_depth >= 8 * out.dtype.itemsize:
            return
        if (int(out.max()) if peak is None else peak) < 1 << spec.bit_depth:
            return
        for i in range(len(out)):
            spec.check(out[i], label(i), fix)

    def append(self, index: int, image: np.ndarray) -> None:
        """Write frame ``index`` (the next in the sequence); on disk (not yet synced) when this
        returns."""
        raise RunError(f"{self.path}: frames in format {self.format_id!r} are read-only; new "
                       f"scans write {CURRENT_FORMAT!r}.")

    def sync(self) -> None:
        """Make every frame appended so far durable (one fsync)."""

    def close(self) -> None:
        """Finish writing the view: every appended frame is durable when this returns."""

    def _missing(self, what: str) -> RunError:
        return RunError(f"{what} of view {self.view} is missing or unreadable in {self.path}; "
                        f"the view cannot be reconstructed from it. Re-capture it with "
                        f"`dotshell resume {self.root} --view {self.view}` (the damaged frames "
                        "are kept aside), or, if it cannot be, mark it lost so the run completes "
                        f"from the other views: `dotshell lose-view {self.root} {self.view} "
                        "--reason TEXT`.")

    def _check_index(self, index: int) -> str:
        if not 0 <= index < len(self.names):
            raise RunError(f"view {self.view} has {len(self.names)} frames in its sequence; "
                           f"there is no frame {index}.")
        return self.names[index]


class _WriteThrough:
    """The stack's open file as tifffile sees it: without a file number, so pages are written
    with ``write()`` (a full disk raises ``OSError(ENOSPC)``) instead of numpy's ``tofile``,
    which reports a short write as "N requested and M written" with no error number."""

    def __init__(self, f: BinaryIO) -> None:
        self._f = f

    def fileno(self) -> int:
        raise io.UnsupportedOperation("fileno")

    def write(self, data: bytes) -> int:
        return self._f.write(data)

    def seek(self, offset: int, whence: int = 0) -> int:
        return self._f.seek(offset, whence)

    def tell(self) -> int:
        return self._f.tell()

    def flush(self) -> None:
        self._f.flush()

    def seekable(self) -> bool:
        return True

    def writable(self) -> bool:
        return True


class TiffFrameStore(FrameStore):
    """``frames/view_NNN.tif``: one uncompressed page per frame, named in its description."""

    format_id = TIFF_STACK

    def __init__(self, root: Path, view: int, names: Sequence[str]) -> None:
        super().__init__(root, view, names)
        self._file: BinaryIO | None = None
        self._tiff: tifffile.TiffWriter | None = None
        self._written = 0

    @property
    def path(self) -> Path:
        return self.root / RunLayout.frame_stack(self.view)

    def count(self) -> int:
        if not self.path.is_file():
            return 0
        with self._open_read() as f:
            return len(self._pages(f))

    def read_one(self, index: int) -> np.ndarray:
        name = self._check_index(index)
        with self._open_read() as f:
            pages = self._pages(f, index + 1)
            if index >= len(pages):
                raise self._missing(f"frame {index} ({name!r})")
            out = np.empty(pages[index].shape, pages[index].dtype.newbyteorder("="))
            tiffpages.read_into(f, pages[index], out)
            return out

    def read_all(self, spec: FrameSpec | None = None, fix: str = "",
                 out: np.ndarray | None = None) -> np.ndarray:
        with self._open_read() as f:
            pages = self._pages(f)
            if len(pages) < len(self.names):
                raise self._missing(f"frame {len(pages)} ({self.names[len(pages)]!r})")
            first = pages[0]
            shape, dtype = first.shape, first.dtype.newbyteorder("=")
            if spec is not None:
                shape, dtype = (spec.height, spec.width), np.dtype(dtype_for(spec.bit_depth))
            for i, p in enumerate(pages[:len(self.names)]):
                if p.shape != shape or p.dtype.newbyteorder("=") != dtype:
                    odd = np.empty(p.shape, p.dtype.newbyteorder("="))
                    tiffpages.read_into(f, p, odd)
                    self._refuse(odd, self._label(i), np.empty(shape, dtype), spec, fix)
            if out is None or out.shape != (len(self.names), *shape) or out.dtype != dtype \
                    or not (out.flags.c_contiguous and out.flags.writeable):
                out = np.empty((len(self.names), *shape), dtype)
            peak = 0
            for i in range(len(self.names)):
                tiffpages.read_into(f, pages[i], out[i])
                if spec is not None:  # while the frame is in the cache
                    peak = max(peak, int(out[i].max()))
        self._check_values(out, spec, fix, self._label, peak)
        return out

    def _label(self, index: int) -> str:
        return f"frame {self.names[index]!r} (page {index}) of {self.path}"

    def _open_read(self) -> io.FileIO:
        try:
            return open(self.path, "rb", buffering=0)
        except FileNotFoundError:
            raise self._missing("the frame stack") from None

    def _pages(self, f: BinaryIO, stop_after: int | None = None) -> list[tiffpages.Page]:
        """The file's complete pages (the first ``stop_after``), each checked to be the frame
        the run's sequence has there."""
        try:
            pages = tiffpages.read_pages(f, os.fstat(f.fileno()).st_size, stop_after)
        except tiffpages.TiffPageError as exc:
            raise RunError(f"{self.path} is not a readable frame stack ({exc}); view "
                           f"{self.view} cannot be reconstructed from it.") from None
        for i, page in enumerate(pages[:len(self.names)]):
            if page.description != self.names[i]:
                raise RunError(f"{self.path}: page {i} holds frame {page.description!r} where "
                               f"the run's sequence has {self.names[i]!r}; the file does not "
                               "belong to this run's manifest.")
        return pages

    def append(self, index: int, image: np.ndarray) -> None:
        name = self._check_index(index)
        check_image(image, f"frame {name!r} of view {self.view}")
        if index != self._written:
            raise RunError(f"view {self.view}: frame {index} ({name!r}) arrived after "
                           f"{self._written} frames; frames are stored in capture order.")
        if self._tiff is None or self._file is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = open(self.path, "wb")  # noqa: SIM115 (held open until close())
            big = image.nbytes * len(self.names) > _TIFF_LIMIT_BYTES
            # tifffile writes to any object with write/seek/tell; its annotation names IO[bytes]
            self._tiff = tifffile.TiffWriter(_WriteThrough(self._file), bigtiff=big)  # type: ignore[arg-type]
        self._tiff.write(image, contiguous=False, metadata=None, description=name,
                         software="dotshell")
        self._file.flush()  # in the OS's hands: a crash of this process keeps the frame
        self._written += 1

    def sync(self) -> None:
        if self._file is not None:
            self._file.flush()
            os.fsync(self._file.fileno())
            fsync_path(self.path.parent)

    def close(self) -> None:
        if self._tiff is None or self._file is None:
            return
        try:
            self._tiff.close()
            self.sync()
        finally:
            self._file.close()
            self._tiff = self._file = None


class PngFrameStore(FrameStore):
    """``frames/view_NNN/III_NAME.png``: the frame layout of runs before ``tiff-stack/1``."""

    format_id = PNG_FILES

    @property
    def path(self) -> Path:
        return self.root / RunLayout.frame_folder(self.view)

    def frame_path(self, index: int) -> Path:
        return self.path / RunLayout.png_frame(index, self._check_index(index))

    def count(self) -> int:
        return sum(self.frame_path(i).is_file() for i in range(len(self.names)))

    def read_one(self, index: int) -> np.ndarray:
        img = cv2.imread(str(self.frame_path(index)), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise self._missing(self.frame_path(index).name)
        return img

    def read_all(self, spec: FrameSpec | None = None, fix: str = "",
                 out: np.ndarray | None = None) -> np.ndarray:
        out = None  # PNG files decode into new arrays anyway
        for i in range(len(self.names)):
            frame = self.read_one(i)
            self._refuse(frame, str(self.frame_path(i)), None if out is None else out[0],
                         spec, fix)
            if out is None:
                out = np.empty((len(self.names), *frame.shape), frame.dtype)
            out[i] = frame
        assert out is not None, "a view has at least one frame"
        self._check_values(out, spec, fix, lambda i: str(self.frame_path(i)))
        return out


FORMATS: dict[str, type[FrameStore]] = {TIFF_STACK: TiffFrameStore, PNG_FILES: PngFrameStore}


def open_frames(root: Path, view: int, manifest: dict) -> FrameStore:
    """The frame store of ``view`` in the run at ``root``, in the format its ``manifest``
    records (runs without ``frame_format`` are PNG)."""
    fmt = manifest.get("frame_format", PNG_FILES)
    if fmt not in FORMATS:
        raise RunError(f"{root}: frames are stored as {fmt!r}, which this dotshell cannot read "
                       f"(it reads {', '.join(FORMATS)}); update dotshell.")
    return FORMATS[fmt](root, view, manifest["frame_names"])


def frames_on_disk(root: Path, manifest: dict) -> list[int]:
    """How many whole frames each view of the run at ``root`` has on disk, in view order: what
    the stacks hold, whatever the manifest recorded (a stack cut short by a copy, or deleted,
    counts what is left; a page cut in the middle does not count)."""
    return [open_frames(Path(root), v["index"], manifest).count() if v.get("frames") else 0
            for v in manifest["views"]]


def damaged_views(root: Path, manifest: dict) -> list[tuple[int, int, int]]:
    """(view, frames on disk, frames recorded) of every view recorded complete whose frames
    on disk are fewer (cut or deleted after the scan), unless it is marked lost."""
    return [(v["index"], n, v["frames"]) for v, n in zip(manifest["views"],
                                                         frames_on_disk(root, manifest))
            if v.get("complete") and not is_lost(v) and n < v["frames"]]


def set_aside_partial(root: Path, view: int) -> None:
    """Move the frames of an unfinished view of the run at ``root`` out of the way (kept, never
    deleted): its frame stack ``frames/view_NNN.tif`` and directory ``frames/view_NNN/`` (frame
    metadata; PNG frames of runs before TIFF stacks) become ``view_NNN.partial-K.tif`` and
    ``view_NNN.partial-K/``."""
    root, L = Path(root), RunLayout
    found = [p for p in (root / L.frame_folder(view), root / L.frame_stack(view))
             if p.is_file() or (p.is_dir() and any(p.iterdir()))]
    if not found:
        return
    k = 1
    while any((root / f"{L.set_aside(view, k)}{s}").exists() for s in ("", ".tif")):
        k += 1
    for p in found:
        p.rename(root / f"{L.set_aside(view, k)}{p.suffix}")


def export_png(frames: FrameStore, out_dir: Path) -> list[Path]:
    """Write the view's frames losslessly as ``out_dir/view_NNN/III_NAME.png`` (the PNG layout,
    same bit depth); returns the files written."""
    d = Path(out_dir) / RunLayout.view_stem(frames.view)
    d.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, name in enumerate(frames.names[:frames.count()]):
        p = d / RunLayout.png_frame(i, name)
        if not cv2.imwrite(str(p), frames.read_one(i), [cv2.IMWRITE_PNG_COMPRESSION, 1]):
            raise RunError(f"could not write {p}; check that {out_dir} is writable.")
        paths.append(p)
    return paths
