"""OpenCV's structured-light Gray-code sequence, built from OpenCV's documented algorithm and
independent of dotshell's coder (tests only; nothing here is imported by dotshell).

The facts, read from opencv_contrib ``modules/structured_light`` (commit 2a5154a, June 2026):

* ``GrayCodePattern_Impl::computeNumberOfPatternImages``: ``ceil(log2(width))`` column images
  and ``ceil(log2(height))`` row images, each with its inverse;
* ``GrayCodePattern_Impl::generate``: for projector column ``j`` and ``k = 0 … n − 1`` the
  image at index ``2n − 2k − 2`` is ``flag · 255`` with ``flag = 1`` where bit ``k + 1`` of ``j``
  differs from bit ``k`` — bit ``k`` of the Gray code ``j ^ (j >> 1)`` — and the image after it
  is the inverse. So the coarsest bit comes first and the FIRST image of each pair is lit where
  the Gray bit is 1. Row images follow all column images, made the same way from the row
  index;
* ``samples/cap_pattern.cpp`` appends ``getImagesForShadowMasks``' white image, then the black
  one, and saves camera frame ``i`` (0-based) as ``pattern_cam1_im{i + 1}.png``.

``tests/test_captures.py`` checks these images against opencv-contrib's own ``generate()``
where ``.venv-bench-contrib`` (created by ``make bench``) is present.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

LAYOUTS = Path(__file__).resolve().parents[1] / "layouts"


def image_count(size: int) -> int:
    """Bit images of one projector axis: ceil(log2 size)."""
    return int(math.ceil(math.log2(size)))


def _axis_images(size: int) -> list[np.ndarray]:
    """0/255 vectors over one projector axis, in OpenCV's order (pattern, inverse per bit)."""
    n = image_count(size)
    index = np.arange(size)
    images: list[np.ndarray] = [np.empty(0)] * (2 * n)
    for k in range(n):
        flag = ((index >> (k + 1)) & 1) != ((index >> k) & 1)
        images[2 * n - 2 * k - 2] = np.where(flag, 255, 0).astype(np.uint8)
        images[2 * n - 2 * k - 1] = np.where(flag, 0, 255).astype(np.uint8)
    return images


def generate(width: int, height: int) -> list[np.ndarray]:
    """The images of GrayCodePattern::generate() for a (width, height) projector (uint8)."""
    cols = [np.ascontiguousarray(np.broadcast_to(v[None, :], (height, width)))
            for v in _axis_images(width)]
    rows = [np.ascontiguousarray(np.broadcast_to(v[:, None], (height, width)))
            for v in _axis_images(height)]
    return cols + rows


def capture_sequence(width: int, height: int) -> list[np.ndarray]:
    """What cap_pattern.cpp projects: generate()'s images, then white, then black."""
    return generate(width, height) + [np.full((height, width), 255, np.uint8),
                                      np.zeros((height, width), np.uint8)]


def file_name(position: int) -> str:
    """cap_pattern.cpp's name of the frame at ``position`` (0-based) for camera 1."""
    return f"pattern_cam1_im{position + 1}.png"


def write_stretched(directory: Path, projector: tuple[int, int], camera: tuple[int, int],
                    dark_columns: int = 0) -> np.ndarray:
    """Write the capture sequence as a camera sees it that sees the projector stretched over its
    image (projector column = (x + 0.5) · W / camera width − 0.5; levels 20 dark, 220 lit;
    the first ``dark_columns`` camera columns unlit). Returns the true column of each camera
    column."""
    pw, ph = projector
    cw, ch = camera
    cols = np.floor((np.arange(cw) + 0.5) * pw / cw).astype(int)
    rows = np.floor((np.arange(ch) + 0.5) * ph / ch).astype(int)
    directory.mkdir(parents=True, exist_ok=True)
    for i, img in enumerate(capture_sequence(pw, ph)):
        seen = (img[rows][:, cols].astype(np.uint16) * 200 // 255 + 20).astype(np.uint8)
        seen[:, :dark_columns] = 20
        cv2.imwrite(str(directory / file_name(i)), seen)
    return (np.arange(cw) + 0.5) * pw / cw - 0.5


def layout_file(path: Path, projector: tuple[int, int]) -> Path:
    """The shipped opencv-graycode layout with its projector size set, written to ``path``."""
    text = (LAYOUTS / "opencv-graycode.toml").read_text()
    text = text.replace("projector_width = 1024", f"projector_width = {projector[0]}")
    path.write_text(text.replace("projector_height = 768", f"projector_height = {projector[1]}"))
    return path
