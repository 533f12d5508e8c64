"""XOR codes (Gupta, Agrawal, Veeraraghavan, Narasimhan, CVPR 2011): gray code whose patterns
are all high-frequency, so long-range global light (subsurface scattering, diffusion,
inter-reflections) adds about equally to every pattern and its inverse and cancels.

A base pattern is chosen among the Gray-code bits: the finest bit (stripes 2 projector pixels
wide: XOR-02) or the second finest (stripes 4 pixels wide: XOR-04). The base is projected as it
is; every other bit ``g_i`` is projected as ``g_i XOR base``. Decoding decides each projected
bit as the gray code does (contrast or robust classification, pattern vs inverse) and XORs the
decided bits back with the decided base bit.

On a stripe edge of the base every projected pattern flips at once, so there all projected
bits are weak together while the Gray bits other than the base do not change. There the Gray
bits other than the base are taken from the 5×5 neighbours where both the projected bit and
the base are surely decided (when those neighbours agree); the base itself is then the single
weak bit the gray code tolerates on its own edge. Sub-pixel stripe edges, centring, inverses,
``drop_low_bits`` and every other setting work as in :mod:`dotshell_codings.graycode`.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import cv2
import numpy as np

from dotshell_codings.graycode import SETTINGS_SCHEMA as GRAY_SETTINGS
from dotshell_codings.graycode import GrayCode, _Axis

#: the gray code's settings, with ``robust`` the default classification: the adaptive rescue
#: adds wrong codes to the XOR codes (synthetic clean scene: XOR-02 3.1 → 5.4 % of the pixels;
#: docs/codings.md)
SETTINGS_SCHEMA = {**GRAY_SETTINGS,
                   "classification": replace(GRAY_SETTINGS["classification"], default="robust")}

#: base stripe width (projector pixels) → position of the base bit counted from the finest
BASE_FROM_END = {2: 1, 4: 2}
_BOX = (5, 5)


class XorCode(GrayCode):
    """XOR-02 (``base_stripe_px = 2``) or XOR-04 (``base_stripe_px = 4``) code."""

    def __init__(self, base_stripe_px: int = 4, classification: str = "robust",
                 **settings: Any) -> None:
        if base_stripe_px not in BASE_FROM_END:
            raise ValueError(f"XOR base stripe width must be 2 or 4 projector pixels, not "
                             f"{base_stripe_px}")
        super().__init__(classification=classification, **settings)
        self.base_stripe_px = base_stripe_px
        self.label = f"XOR-0{base_stripe_px} code"

    def base_bit(self, ax: _Axis) -> int:
        """Index (MSB first) of the base bit among the axis' projected bits."""
        b = ax.nb - BASE_FROM_END[self.base_stripe_px]
        if b < 0:
            raise ValueError(f"the {self.label} needs at least {BASE_FROM_END[self.base_stripe_px]}"
                             f" bits on the projector {ax.prefix} axis; use a smaller "
                             "drop_low_bits")
        return b

    def projected_stripes(self, ax: _Axis, i: int) -> np.ndarray:
        b = self.base_bit(ax)
        base = ax.bit_stripes(b)
        return base if i == b else ax.bit_stripes(i) ^ base

    def high_frequency_bits(self, ax: _Axis) -> list[int]:
        """Every projected XOR pattern is high-frequency (that is the point of the code)."""
        return list(range(ax.nb))

    def refine_anchors(self, ax: _Axis) -> tuple[int | None, int]:
        """Only the base's edges: its pattern is a clean square wave, while the other projected
        patterns have stripes as narrow as half the base stripe next to their own edges."""
        return self.base_bit(ax), 1 << BASE_FROM_END[self.base_stripe_px]

    def sign_base(self, ax: _Axis) -> int:
        """The base bit: every other projected bit is the Gray bit XOR the base."""
        return self.base_bit(ax)

    def gray_words(self, ax: _Axis, value: np.ndarray, weak: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Gray bits = projected bits XOR the base bit, bit by bit (:func:`_unxor`)."""
        b = self.base_bit(ax)
        shift = np.uint32(ax.nb - 1 - b)
        base = ((value >> shift) & 1).astype(bool)
        base_weak = ((weak >> shift) & 1).astype(bool)
        gray = value & (np.uint32(1) << shift)
        gray_weak = weak & (np.uint32(1) << shift)
        for i in range(ax.nb):
            if i == b:
                continue
            s = np.uint32(ax.nb - 1 - i)
            g, g_weak = _unxor(((value >> s) & 1).astype(bool), ((weak >> s) & 1).astype(bool),
                               base, base_weak)
            gray |= g.astype(np.uint32) << s
            gray_weak |= g_weak.astype(np.uint32) << s
        return gray, gray_weak


def _unxor(x: np.ndarray, x_weak: np.ndarray, base: np.ndarray, base_weak: np.ndarray,
           ) -> tuple[np.ndarray, np.ndarray]:
    """Gray bit = projected bit XOR base; where the base is weak, from agreeing neighbours."""
    g = x ^ base
    sure = ~x_weak & ~base_weak
    if not base_weak.any():
        return g, x_weak
    ones = cv2.boxFilter((g & sure).view(np.uint8), cv2.CV_16U, _BOX, normalize=False)
    zeros = cv2.boxFilter((~g & sure).view(np.uint8), cv2.CV_16U, _BOX, normalize=False)
    fill_one = base_weak & (ones > 0) & (zeros == 0)
    fill_zero = base_weak & (zeros > 0) & (ones == 0)
    g = np.where(base_weak, fill_one, g)
    weak = np.where(base_weak, ~(fill_one | fill_zero), x_weak)
    return g, weak


def xor_factory(base_stripe_px: int):
    """Backend factory for the XOR code with the given base stripe width."""
    def make(settings: dict[str, Any] | None = None, context: Any = None) -> XorCode:
        s = {name: spec.default for name, spec in SETTINGS_SCHEMA.items()}
        s.update(settings or {})
        return XorCode(base_stripe_px=base_stripe_px, **s)
    return make
