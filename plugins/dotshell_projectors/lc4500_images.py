"""Binary patterns ↔ the 24-bit images a LightCrafter 4500 stores in its flash.

In pattern mode the DLPC350 displays 1-bit patterns as bit planes of 24-bit images kept in
flash: pattern number 0–23 of an image is bit plane G0–G7, R0–R7, B0–B7
(:func:`dotshell_projectors.dlpc350.plane_of`). :func:`pack` lays a coding's patterns out that
way; the images are put in the projector's flash with TI's LightCrafter 4500 GUI (firmware
build, "Images" list, in the order written); the profile's ``flash_images`` lists the same
files, from which the driver finds each pattern's image and pattern number (:class:`Planes`).

Command line: ``python -m dotshell_projectors.lc4500_pack PROFILE OUT_DIR`` (module
:mod:`dotshell_projectors.lc4500_pack`).
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from dotshell.errors import DeviceError
from dotshell_projectors.dlpc350 import HEIGHT, WIDTH, plane_of

PLANES_PER_IMAGE = 24


def binary(pattern: np.ndarray) -> np.ndarray | None:
    """The pattern as a bool array if it is binary (only 0 and 255, or bool), else None."""
    p = np.asarray(pattern)
    if p.dtype == np.bool_:
        return p
    if p.dtype != np.uint8 or not np.all((p == 0) | (p == 255)):
        return None
    return p == 255


def pack(patterns: Sequence[np.ndarray]) -> list[np.ndarray]:
    """24-bit RGB images (HEIGHT, WIDTH, 3) uint8 holding ``patterns`` (binary, HEIGHT × WIDTH)
    as bit planes, pattern k in image k // 24 at pattern number k % 24."""
    images = []
    for k, p in enumerate(patterns):
        bits = binary(p)
        if bits is None or bits.shape != (HEIGHT, WIDTH):
            raise ValueError(f"pattern {k} must be a binary {WIDTH}x{HEIGHT} image (0/255).")
        if k % PLANES_PER_IMAGE == 0:
            images.append(np.zeros((HEIGHT, WIDTH, 3), np.uint8))
        channel, bit = plane_of(k % PLANES_PER_IMAGE)
        images[-1][..., channel] |= bits.astype(np.uint8) << bit
    return images


def _digest(bits: np.ndarray) -> bytes:
    return hashlib.blake2b(np.packbits(bits).tobytes(), digest_size=16).digest()


class Planes:
    """Where each bit plane of the flash images is: (image index, pattern number) by content."""

    def __init__(self, images: Sequence[np.ndarray]) -> None:
        self.count = len(images)
        self.where: dict[bytes, tuple[int, int]] = {}
        for i, img in enumerate(images):
            if img.shape != (HEIGHT, WIDTH, 3):
                raise DeviceError(f"LightCrafter 4500: flash image {i} is {img.shape[1]}x"
                                  f"{img.shape[0]}; the DLPC350 stores {WIDTH}x{HEIGHT} 24-bit "
                                  "images.")
            for number in range(PLANES_PER_IMAGE):
                channel, bit = plane_of(number)
                self.where.setdefault(_digest((img[..., channel] >> bit) & 1 == 1), (i, number))

    def locate(self, pattern: np.ndarray) -> tuple[int, int] | None:
        """(image index, pattern number) of a binary pattern stored in flash, else None."""
        bits = binary(pattern)
        if bits is None or bits.shape != (HEIGHT, WIDTH):
            return None
        return self.where.get(_digest(bits))


def load(paths: Sequence[str | Path]) -> list[np.ndarray]:
    """Flash images (RGB) from image files; a DeviceError naming an unreadable one."""
    out = []
    for p in paths:
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if img is None:
            raise DeviceError(f"LightCrafter 4500: cannot read flash image {p}; list the 24-bit "
                              "images stored in the projector's flash in [projector.settings] "
                              "flash_images (python -m dotshell_projectors.lc4500_pack writes "
                              "them).")
        out.append(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
    return out


def save(images: Sequence[np.ndarray], out_dir: Path) -> list[Path]:
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, img in enumerate(images):
        path = out_dir / f"lc4500_{i:02d}.png"
        cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        paths.append(path)
    return paths
