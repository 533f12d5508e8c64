"""Peer decoder: OpenCV contrib's ``cv2.structured_light.GrayCodePattern.getProjPixel``.

Runs inside ``.venv-bench-contrib`` (numpy + opencv-contrib-python-headless only; it must not
import dotshell) as a small server, so the bench can interleave its timings with dotshell's:
``python peer_opencv.py JOB_JSON OUT_NPZ``, then one command per line on stdin:

* ``time`` — decode every lit pixel once with getProjPixel, in raster order (row by row, as
  OpenCV's own ``decode()`` visits them), and answer one line ``{"seconds": s}``;
* ``done`` — write the results of the last run to OUT_NPZ and exit.

The job names:

* ``frames``: a ``.npy`` stack already in OpenCV's order — for each column bit (MSB first) the
  pattern then its inverse, then the same for rows, then white, then black;
* ``projector``: [width, height] px; ``shift``: right shift that brings the frames to 8 bit
  (getProjPixel reads 8-bit pixels);
* ``white_threshold`` / ``black_threshold``: 8-bit DN thresholds (OpenCV's defaults 5 / 40).

Lit pixels are those OpenCV's ``decode()`` would decode: white − black > the black threshold.
getProjPixel itself tests the pattern/inverse contrast (white threshold) and whether the decoded
pixel lies inside the projector.

Writes ``xs, ys`` (the lit pixels), ``col, row`` (decoded projector pixel), ``error`` (True
where getProjPixel reported an error), and ``cv2_version``.
"""

from __future__ import annotations

import json
import sys
import time

import cv2
import numpy as np


def load_frames(path: str, shift: int) -> list[np.ndarray]:
    """The stack as 8-bit frames (``>> shift``)."""
    stack = np.load(path)
    return [np.ascontiguousarray((f >> shift).astype(np.uint8)) for f in stack]


def main(job_path: str, out_path: str) -> None:
    job = json.loads(open(job_path).read())
    frames = load_frames(job["frames"], job["shift"])
    width, height = job["projector"]
    gc = cv2.structured_light.GrayCodePattern.create(width, height)
    gc.setWhiteThreshold(job["white_threshold"])
    gc.setBlackThreshold(job["black_threshold"])
    white, black = frames[-2].astype(np.int16), frames[-1].astype(np.int16)
    ys, xs = np.nonzero(white - black > job["black_threshold"])  # raster order
    xs_l, ys_l = xs.tolist(), ys.tolist()
    n = len(xs_l)
    col, row, error = [0] * n, [0] * n, [False] * n
    print(json.dumps({"lit": n, "cv2_version": cv2.__version__}), flush=True)
    for line in sys.stdin:
        if line.strip() == "done":
            break
        t0 = time.perf_counter()
        for i in range(n):
            err, (px, py) = gc.getProjPixel(frames, xs_l[i], ys_l[i])
            error[i], col[i], row[i] = err, px, py
        print(json.dumps({"seconds": time.perf_counter() - t0}), flush=True)
    np.savez(out_path, xs=xs, ys=ys, col=np.array(col, np.int32), row=np.array(row, np.int32),
             error=np.array(error, bool), cv2_version=cv2.__version__)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
