"""How the frame format was chosen: write, read and size of one full-resolution view in each
candidate lossless format (docs/performance.md, "Frame storage").

Usage: ``.venv/bin/python benchmarks/frame_formats.py [--repeats N] [--out DIR]``. Renders view 0
of the reference bench with the simulator (42 frames, 1280×1024 uint16), then for each candidate
writes the view frame by frame (as a scan does), fsyncs it once, reads it back warm (page cache)
and cold (pages dropped with ``posix_fadvise``), reads one frame, and checks every pixel.
zarr and imagecodecs are not dotshell dependencies: candidates needing them are skipped unless
installed (``.venv/bin/pip install zarr imagecodecs``). ``--out`` must be on the disk whose
speed matters (default: a temporary directory under ``bench-results/``).
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import tempfile
import time
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import tifffile

from bench_profile import ROOT, load_bench_profile
from dotshell.runtime.process import configure_process
from dotshell.plugins import get_plugin_manager
from run import render_view

ONE = 17  # the frame read alone

Writer = Callable[[Path, np.ndarray], None]
Reader = Callable[[Path], np.ndarray]
OneReader = Callable[[Path], np.ndarray]


def _png() -> tuple[Writer, Reader, OneReader]:
    def write(d: Path, stack: np.ndarray) -> None:
        d.mkdir()
        for i, f in enumerate(stack):
            ok, buf = cv2.imencode(".png", f, [cv2.IMWRITE_PNG_COMPRESSION, 1])
            (d / f"{i:03d}.png").write_bytes(buf.tobytes())

    def read(d: Path) -> np.ndarray:
        return np.stack([cv2.imread(str(d / f"{i:03d}.png"), cv2.IMREAD_UNCHANGED)
                         for i in range(len(list(d.iterdir())))])

    return write, read, lambda d: cv2.imread(str(d / f"{ONE:03d}.png"), cv2.IMREAD_UNCHANGED)


def _tiff(compression: str | None, level: int | None = None) -> tuple[Writer, Reader, OneReader]:
    def write(d: Path, stack: np.ndarray) -> None:
        d.mkdir()
        kw = {} if compression is None else {"compression": compression,
                                             "compressionargs": {"level": level},
                                             "predictor": "horizontal"}
        with tifffile.TiffWriter(d / "frames.tif") as tw:
            for f in stack:
                tw.write(f, contiguous=False, metadata=None, **kw)

    def read(d: Path) -> np.ndarray:
        return tifffile.imread(d / "frames.tif", key=slice(None))

    return write, read, lambda d: tifffile.imread(d / "frames.tif", key=ONE)


def _zarr(cname: str, shuffle: str) -> tuple[Writer, Reader, OneReader]:
    import zarr
    from zarr.codecs import BloscCodec

    def write(d: Path, stack: np.ndarray) -> None:
        z = zarr.create_array(store=str(d), shape=stack.shape, chunks=(1, *stack.shape[1:]),
                              dtype=stack.dtype, fill_value=0,
                              compressors=BloscCodec(cname=cname, clevel=1, shuffle=shuffle))
        for i, f in enumerate(stack):
            z[i] = f

    def read(d: Path) -> np.ndarray:
        return zarr.open_array(str(d), mode="r")[:]

    return write, read, lambda d: zarr.open_array(str(d), mode="r")[ONE]


def candidates() -> dict[str, Callable[[], tuple[Writer, Reader, OneReader]]]:
    return {
        "PNG level 1, one file per frame (cv2)": _png,
        "TIFF stack, uncompressed (tifffile)": lambda: _tiff(None),
        "TIFF stack, zstd 1 + predictor (imagecodecs)": lambda: _tiff("zstd", 1),
        "zarr v3, blosc zstd 1 + bitshuffle": lambda: _zarr("zstd", "bitshuffle"),
        "zarr v3, blosc lz4 + bitshuffle": lambda: _zarr("lz4", "bitshuffle"),
        "zarr v3, blosc lz4 + byte shuffle": lambda: _zarr("lz4", "shuffle"),
    }


def _files(d: Path) -> list[Path]:
    return [p for p in d.rglob("*") if p.is_file()]


def _fsync(d: Path) -> None:
    for p in [*_files(d), *[q for q in d.rglob("*") if q.is_dir()], d]:
        fd = os.open(p, os.O_RDONLY)
        os.fsync(fd)
        os.close(fd)


def _drop_cache(d: Path) -> None:
    for p in _files(d):
        fd = os.open(p, os.O_RDONLY)
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        os.close(fd)


def _ms(values: list[float]) -> str:
    return f"{min(values) * 1e3:6.0f} / {statistics.median(values) * 1e3:6.0f}"


def measure(name: str, make, stack: np.ndarray, work: Path, repeats: int) -> None:
    try:
        write, read, read_one = make()
    except ImportError as exc:
        print(f"  {name:46s} skipped ({exc.name} not installed)")
        return
    t: dict[str, list[float]] = {k: [] for k in ("write", "fsync", "warm", "cold", "one")}
    size = 0
    for r in range(repeats):
        d = work / f"c{r}"
        shutil.rmtree(d, ignore_errors=True)
        for key, fn in (("write", lambda: write(d, stack)), ("fsync", lambda: _fsync(d))):
            t0 = time.perf_counter()
            fn()
            t[key].append(time.perf_counter() - t0)
        for key in ("warm", "cold"):
            if key == "cold":
                _drop_cache(d)
            t0 = time.perf_counter()
            back = read(d)
            t[key].append(time.perf_counter() - t0)
            if not np.array_equal(back, stack):
                raise AssertionError(f"{name}: frames did not read back as written")
            del back
        t0 = time.perf_counter()
        one = read_one(d)
        t["one"].append(time.perf_counter() - t0)
        assert np.array_equal(one, stack[ONE])
        size = sum(p.stat().st_size for p in _files(d))
        shutil.rmtree(d)
    print(f"  {name:46s} {_ms(t['write'])}  {_ms(t['fsync'])}  {_ms(t['warm'])}  "
          f"{_ms(t['cold'])}  {_ms(t['one'])}  {size / 1e6:6.1f} ({100 * size / stack.nbytes:3.0f} %)",
          flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None, help="scratch directory (its disk)")
    args = ap.parse_args()
    configure_process()
    pm = get_plugin_manager()
    stack = render_view(load_bench_profile(pm, False), pm).frames
    parent = args.out or ROOT / "bench-results"
    parent.mkdir(parents=True, exist_ok=True)
    print(f"{len(stack)} frames {stack.shape[2]}x{stack.shape[1]} {stack.dtype}, "
          f"{stack.nbytes / 1e6:.1f} MB raw; 1-min load {os.getloadavg()[0]:.1f}; "
          f"ms min / median of {args.repeats}")
    print(f"  {'format':46s} {'write':>15s}  {'fsync':>15s}  {'read warm':>15s}  "
          f"{'read cold':>15s}  {'read one':>15s}  {'MB (of raw)':>14s}")
    with tempfile.TemporaryDirectory(dir=parent, prefix="frame-formats-") as tmp:
        for name, make in candidates().items():
            measure(name, make, stack, Path(tmp), args.repeats)


if __name__ == "__main__":
    main()
