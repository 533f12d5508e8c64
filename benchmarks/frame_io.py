"""Frame I/O of one view: the PNG files runs used to write against the TIFF stack they write now.

Each repeat writes the view both ways into a fresh directory, then reads it back both ways,
alternating the formats so that machine load hits both alike:

* PNG write: the old path, per frame PNG level 1 (``cv2.imencode``) + an atomic write with an
  fsync per frame (``RunStore.write_image``);
* TIFF write: :class:`dotshell.run.frames.TiffFrameStore` — every frame appended as it would arrive,
  one fsync at the end of the view (``close``);
* read all (every frame of the view, from the page cache as ``dotshell reconstruct`` does right
  after a scan) and read one (frame 17, a preview);
* size on disk.
"""

from __future__ import annotations

import shutil
import statistics
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from dotshell.run.frames import PngFrameStore, TiffFrameStore
from dotshell.run.store import RunStore


def _write_png(root: Path, view: int, names: list[str], frames: np.ndarray) -> None:
    store, png = RunStore(root), PngFrameStore(root, view, names)
    for i in range(len(names)):
        store.write_image(png.frame_path(i), frames[i], f"frame {i}")


def _write_tiff(root: Path, view: int, names: list[str], frames: np.ndarray) -> None:
    tiff = TiffFrameStore(root, view, names)
    for i in range(len(names)):
        tiff.append(i, frames[i])
    tiff.close()


def _timed(fn: Callable[[], Any]) -> tuple[float, Any]:
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def _size(path: Path) -> int:
    return path.stat().st_size if path.is_file() else sum(p.stat().st_size
                                                          for p in path.iterdir())


def min_median(values: list[float]) -> dict[str, float]:
    """``{"min": ..., "median": ...}`` of timings in seconds."""
    return {"min": min(values), "median": statistics.median(values)}


def measure(frames: np.ndarray, names: list[str], work: Path, repeats: int) -> dict[str, Any]:
    """Write/read seconds (min and median of ``repeats``) and bytes per view, both formats."""
    runs: dict[str, list[float]] = {}
    sizes = {}
    writers = {"png": _write_png, "tiff": _write_tiff}
    stores = {"png": PngFrameStore, "tiff": TiffFrameStore}
    for r in range(repeats):
        root = work / f"frame-io-{r}"
        order = ("png", "tiff") if r % 2 == 0 else ("tiff", "png")
        for fmt in order:
            s, _ = _timed(lambda: writers[fmt](root, 0, names, frames))
            runs.setdefault(f"{fmt}_write", []).append(s)
        for fmt in order:
            store = stores[fmt](root, 0, names)
            s, back = _timed(store.read_all)
            if not np.array_equal(back, frames):
                raise AssertionError(f"{fmt} frames did not read back as written")
            del back
            runs.setdefault(f"{fmt}_read_all", []).append(s)
            s, _ = _timed(lambda: store.read_one(17))
            runs.setdefault(f"{fmt}_read_one", []).append(s)
            sizes[fmt] = _size(store.path)
        shutil.rmtree(root)
    out: dict[str, Any] = {k: min_median(v) for k, v in runs.items()}
    out.update(repeats=repeats, frames=len(names), raw_bytes=int(frames.nbytes),
               png_bytes=sizes["png"], tiff_bytes=sizes["tiff"])
    return out


def print_frame_io(d: dict[str, Any]) -> None:
    mb = 1e6
    print(f"\n== 1. frame I/O per view ({d['frames']} frames, {d['raw_bytes'] / mb:.0f} MB "
          f"raw; min / median of {d['repeats']}, formats alternated) ==")
    print(f"  {'':34s} {'PNG (runs before)':>20s} {'TIFF stack (now)':>20s} {'ratio':>7s}")
    rows = (("write, synced to disk", "write"), ("read all frames", "read_all"),
            ("read one frame", "read_one"))
    for label, key in rows:
        png, tif = d[f"png_{key}"], d[f"tiff_{key}"]
        print(f"  {label + ' [ms]':34s} {png['min'] * 1e3:9.1f} / {png['median'] * 1e3:7.1f}"
              f"  {tif['min'] * 1e3:9.1f} / {tif['median'] * 1e3:7.1f} "
              f"{png['median'] / tif['median']:6.1f}x")
    print(f"  {'size on disk [MB]':34s} {d['png_bytes'] / mb:20.1f} {d['tiff_bytes'] / mb:20.1f}"
          f" {d['png_bytes'] / d['tiff_bytes']:6.2f}x")
