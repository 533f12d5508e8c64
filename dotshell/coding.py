"""The pattern-coding role: which images a projector shows, and how camera frames of them decode
into projector coordinates per camera pixel. Codings are pure (arrays in, arrays out)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, Sequence, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class PatternFrame:
    """One image to project.

    Attributes:
        name: short unique file-name-safe name, e.g. ``"white"``, ``"col_03"``, ``"col_03_inv"``.
        image: uint8 array (projector height, projector width); 255 is full brightness.
    """

    name: str
    image: np.ndarray


@dataclass
class Correspondence:
    """Decoded projector coordinates for every camera pixel of one view.

    Attributes:
        column: float32 (H, W) projector column in pixels (pixel centres at integers, sub-pixel
            where the coding refines it); NaN where not decoded.
        row: float32 (H, W) projector row, or ``None`` when the coding decodes columns only.
        valid: bool (H, W); True where ``column`` (and ``row`` when present) can be used.
        stats: pixel counts by outcome, e.g. ``{"decoded": n, "shadow": n,
            "low_contrast": n, "uncertain": n}`` — reported in the run's report.
        reason: uint8 (H, W) why each pixel is not decoded, an index into ``reason_names``
            (0 = ``"decoded"``), or ``None`` when the coding does not say (see
            :func:`label_reasons`).
        reason_names: the names of the ``reason`` codes, in code order.
    """

    column: np.ndarray
    row: np.ndarray | None
    valid: np.ndarray
    stats: dict[str, int] = field(default_factory=dict)
    reason: np.ndarray | None = None
    reason_names: tuple[str, ...] = ("decoded",)


def label_reasons(valid: np.ndarray, reasons: dict[str, np.ndarray]
                  ) -> tuple[np.ndarray, tuple[str, ...]]:
    """A uint8 reason map (0 where ``valid``, k where the k-th mask of ``reasons`` holds;
    a pixel in several masks gets the first) and its names ``("decoded", *reasons)``."""
    label = np.zeros(valid.shape, np.uint8)
    for code, mask in reversed(list(enumerate(reasons.values(), start=1))):
        label[mask & ~valid] = code
    return label, ("decoded", *reasons)


@runtime_checkable
class PatternCoding(Protocol):
    """A structured-light code. Implementations are created by a backend factory from settings."""

    def patterns(self, projector_size: tuple[int, int]) -> list[PatternFrame]:
        """The sequence to project for a projector of (width, height) pixels, in order."""
        ...

    def decode(self, frames: Sequence[np.ndarray], projector_size: tuple[int, int]) -> Correspondence:
        """Decode camera frames captured in the order of :meth:`patterns` (same length).

        Frames are 2-D arrays (uint8 or uint16) of one camera, all the same shape.
        """
        ...
