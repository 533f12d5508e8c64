"""Peer decoder: OpenCV contrib's ``cv2.structured_light.GrayCodePattern.getProjPixel``.

Runs inside ``.venv-bench-contrib`` (numpy + opencv-contrib-python-headless only; it must not
import dotshell). Usage: ``python peer_opencv.py JOB_JSON OUT_NPZ``. The job names:

* ``frames``: PNG paths already in OpenCV's order — for each column bit (MSB first) the pattern
  then its inverse, then the same for rows, then white, then black;
* ``projector``: [width, height] px; ``shift``: right shift that brings the frames to 8 bit
  (getProjPixel reads 8-bit pixels);
* ``sample``: number of camera pixels to decode, drawn without replacement with ``seed``;
* ``white_threshold`` / ``black_threshold``: 8-bit DN thresholds (OpenCV's defaults 5 / 40).

getProjPixel tests only the pattern/inverse contrast (white threshold) and whether the decoded
pixel lies inside the projector; the black threshold is used by OpenCV's ``decode()`` shadow
mask (white − black > threshold), which is applied here the same way, outside the timing.

Writes ``xs, ys`` (sampled pixels), ``col, row`` (decoded projector pixel), ``error`` (True where
getProjPixel reported an error), ``lit`` (shadow mask), ``seconds`` (getProjPixel loop only).
"""

from __future__ import annotations

import json
import sys
import time

import cv2
import numpy as np


def load_frames(paths: list[str], shift: int) -> list[np.ndarray]:
    """Read PNGs unchanged and reduce them to 8 bit by ``>> shift``."""
    out = []
    for p in paths:
        img = cv2.imread(p, cv2.IMREAD_UNCHANGED)
        if img is None:
            raise SystemExit(f"peer: cannot read {p}")
        out.append(np.ascontiguousarray((img >> shift).astype(np.uint8)))
    return out


def sample_pixels(shape: tuple[int, int], n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` distinct (x, y) camera pixels of an image of ``shape`` (rows, cols)."""
    h, w = shape
    idx = np.random.default_rng(seed).choice(h * w, size=min(n, h * w), replace=False)
    return (idx % w).astype(np.int32), (idx // w).astype(np.int32)


def main(job_path: str, out_path: str) -> None:
    job = json.loads(open(job_path).read())
    frames = load_frames(job["frames"], job["shift"])
    width, height = job["projector"]
    gc = cv2.structured_light.GrayCodePattern.create(width, height)
    gc.setWhiteThreshold(job["white_threshold"])
    gc.setBlackThreshold(job["black_threshold"])
    xs, ys = sample_pixels(frames[0].shape, job["sample"], job["seed"])
    n = len(xs)
    col, row = np.zeros(n, np.int32), np.zeros(n, np.int32)
    error = np.zeros(n, bool)
    t0 = time.perf_counter()
    for i in range(n):
        err, (px, py) = gc.getProjPixel(frames, int(xs[i]), int(ys[i]))
        error[i], col[i], row[i] = err, px, py
    seconds = time.perf_counter() - t0
    white, black = frames[-2].astype(np.int16), frames[-1].astype(np.int16)
    lit = (white - black)[ys, xs] > job["black_threshold"]
    np.savez(out_path, xs=xs, ys=ys, col=col, row=row, error=error, lit=lit,
             seconds=seconds, cv2_version=cv2.__version__)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
