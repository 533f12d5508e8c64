"""Gray code + N-step phase shifting: the gray code gives a coarse absolute coordinate, the
phase of N shifted sinusoids of period P projector pixels a continuous one.

Sequence (``axes = "both"``): the gray code's frames (white, black, column bits and inverses,
row bits and inverses; ``drop_low_bits = log2(P / 4)`` so the finest Gray stripe is P/4 wide),
then ``col_ps_0 .. col_ps_{N-1}``, then ``row_ps_0 .. row_ps_{N-1}``.

Projector pixel ``c`` of shifted pattern ``k`` shows ``127.5 (1 + cos(2π (c − x0)/P − 2πk/N))``
(rounded to uint8) with ``x0 = −offset − 0.5``, the boundary before code value 0 of the centred
gray code, so the phase origin is centred like the code.

Decoding, per camera pixel and axis:

* phase ``φ = atan2(Σ I_k sin δ_k, Σ I_k cos δ_k)`` (``δ_k = 2πk/N``), taken in [0, 2π);
* modulation ``γ = (2/N) |Σ I_k e^{iδ_k}| / ((white − black)/2)`` — the sinusoid's amplitude
  relative to what a full-contrast pattern gives; ``γ < min_modulation`` marks the pixel
  ``low_modulation`` (shadow edges, blur, and global light, which raises white but not the
  amplitude of a high-frequency sinusoid);
* unwrapping with the absolute coarse coordinate ``u_g`` (the centre of the decoded gray block,
  P/4 wide): period index ``m = round((u_g − x0)/P − φ/2π)``, coordinate
  ``u = x0 + P (m + φ/2π)``. This is robust at period boundaries — the usual failure of
  "period index from the code, phase within the period" — because the gray estimate may be off
  by up to half a period (its error is at most 1.5 blocks = 0.375 P, a block and a half when
  an edge bit is misread) before ``m`` is wrong. Pixels whose ``|u − u_g|`` exceeds
  0.4 P nonetheless are ``phase_inconsistent`` (a gray-code error larger than one block).

Stats: the gray code's (``shadow``, ``low_contrast``, ``uncertain``, ``out_of_range``) plus
``low_modulation`` and ``phase_inconsistent``; all mutually exclusive, summing to ``pixels``.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any, Sequence

import numpy as np

from dotshell.coding import Correspondence, PatternFrame
from dotshell.settings import Setting
from dotshell_codings.graycode import SETTINGS_SCHEMA as GRAY_SETTINGS
from dotshell_codings.graycode import GrayCode, code_offset

_GRAY_KEYS = ("inverse", "classification", "adaptive_sigmas", "adaptive_edge_ratio",
              "adaptive_code_steps", "min_contrast", "direct_min", "high_frequency_pairs",
              "black_level", "shadow_threshold", "bit_depth")
SETTINGS_SCHEMA: dict[str, Setting] = {
    "axes": GRAY_SETTINGS["axes"],
    "period_px": Setting(
        "int", 16, choices=(8, 16, 32, 64), unit="px",
        help="sinusoid period in projector pixels (the finest gray stripe is a quarter of it)"),
    "phase_steps": Setting(
        "int", 4, min=3, max=16,
        help="number N of phase-shifted sinusoids per axis (shifts of 2π/N)"),
    "min_modulation": Setting(
        "float", 0.2, min=0.0, max=1.0,
        help="minimum sinusoid amplitude relative to (white - black)/2; weaker pixels are "
             "low_modulation"),
    **{k: GRAY_SETTINGS[k] for k in _GRAY_KEYS},
    # robust by default: under long-range global light the adaptive rescue adds coarse codes
    # as wrong as robust's (synthetic scene: 51.9 → 52.4 % of the pixels; docs/codings.md)
    "classification": replace(GRAY_SETTINGS["classification"], default="robust"),
}
#: |phase coordinate − gray coordinate| above this many periods → phase_inconsistent
MAX_COARSE_MISMATCH_PERIODS = 0.4


class GrayPhaseCode:
    """Gray code + phase shifting :class:`dotshell.coding.PatternCoding`."""

    def __init__(self, axes: str = "both", period_px: int = 16, phase_steps: int = 4,
                 min_modulation: float = 0.2, **gray_settings: Any) -> None:
        if period_px < 8 or period_px & (period_px - 1):
            raise ValueError(f"period_px must be a power of two >= 8, not {period_px}")
        if phase_steps < 3:
            raise ValueError(f"phase shifting needs at least 3 steps, not {phase_steps}")
        self.period = int(period_px)
        self.steps = int(phase_steps)
        self.min_modulation = float(min_modulation)
        drop = int(round(math.log2(self.period // 4)))
        gray_settings.setdefault("classification", "robust")  # as SETTINGS_SCHEMA says
        self.gray = GrayCode(axes=axes, drop_low_bits=drop, subpixel=False, **gray_settings)

    def _axis_sizes(self, projector_size: tuple[int, int]) -> list[tuple[str, int]]:
        w, h = (int(s) for s in projector_size)
        return [("col", w)] + ([("row", h)] if self.gray.axes == "both" else [])

    def frame_names(self, projector_size: tuple[int, int]) -> list[str]:
        names = self.gray.frame_names(projector_size)
        for prefix, _ in self._axis_sizes(projector_size):
            names += [f"{prefix}_ps_{k}" for k in range(self.steps)]
        return names

    def origin(self, size: int) -> float:
        """Projector coordinate x0 where the phase is 0 (the centred code's origin)."""
        return -code_offset(size) - 0.5

    def patterns(self, projector_size: tuple[int, int]) -> list[PatternFrame]:
        w, h = (int(s) for s in projector_size)
        frames = self.gray.patterns(projector_size)
        for prefix, size in self._axis_sizes(projector_size):
            c = np.arange(size, dtype=np.float64)
            phase = 2 * np.pi * (c - self.origin(size)) / self.period
            for k in range(self.steps):
                s = np.round(127.5 * (1 + np.cos(phase - 2 * np.pi * k / self.steps)))
                s = s.astype(np.uint8)
                img = np.broadcast_to(s[None, :] if prefix == "col" else s[:, None], (h, w))
                frames.append(PatternFrame(f"{prefix}_ps_{k}", np.ascontiguousarray(img)))
        return frames

    def decode(self, frames: Sequence[np.ndarray], projector_size: tuple[int, int]) -> Correspondence:
        axes = self._axis_sizes(projector_size)
        n_phase = self.steps * len(axes)
        n_gray = len(frames) - n_phase
        expected = len(self.gray.frame_names(projector_size)) + n_phase
        if len(frames) != expected:
            raise ValueError(f"gray code + phase shifting expects {expected} frames for "
                             f"projector {tuple(projector_size)}, got {len(frames)}")
        coarse = self.gray.decode(frames[:n_gray], projector_size)
        lv = self.gray.levels(np.asarray(frames[0]), np.asarray(frames[1]))
        half_range = np.maximum(0.5 * lv.range, np.float32(1e-6))
        valid = coarse.valid.copy()
        low_mod = np.zeros(valid.shape, bool)
        inconsistent = np.zeros(valid.shape, bool)
        coords = []
        for a, (prefix, size) in enumerate(axes):
            start = n_gray + a * self.steps
            phi, amp = phase_and_amplitude(frames[start:start + self.steps])
            low_mod |= valid & (amp / half_range < self.min_modulation)
            u_g = coarse.column if prefix == "col" else coarse.row
            u, mismatch = unwrap(phi, u_g, self.origin(size), self.period)
            inconsistent |= valid & (mismatch > MAX_COARSE_MISMATCH_PERIODS * self.period)
            coords.append(u)
        inconsistent &= ~low_mod
        valid &= ~(low_mod | inconsistent)
        for u in coords:
            u[~valid] = np.nan
        stats = dict(coarse.stats)
        stats.pop("edge_tolerated", None)
        stats.update(decoded=int(valid.sum()), low_modulation=int(low_mod.sum()),
                     phase_inconsistent=int(inconsistent.sum()))
        reason, names = coarse.reason, coarse.reason_names
        if reason is not None:
            reason = reason.copy()
            for name, mask in (("low_modulation", low_mod), ("phase_inconsistent", inconsistent)):
                reason[mask & (reason == 0)] = len(names)
                names = (*names, name)
        return Correspondence(column=coords[0], row=coords[1] if len(coords) > 1 else None,
                              valid=valid, stats=stats, reason=reason, reason_names=names)


def phase_and_amplitude(frames: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Phase φ in [0, 2π) and amplitude B of ``I_k = A + B cos(φ − 2πk/N)`` (N = len(frames))."""
    n = len(frames)
    s = np.zeros(np.shape(frames[0]), np.float32)
    c = np.zeros_like(s)
    for k, f in enumerate(frames):
        d = 2 * np.pi * k / n
        f32 = np.asarray(f, dtype=np.float32)
        s += np.float32(math.sin(d)) * f32
        c += np.float32(math.cos(d)) * f32
    phi = np.mod(np.arctan2(s, c), np.float32(2 * np.pi)).astype(np.float32)
    return phi, (2.0 / n) * np.hypot(s, c)


def unwrap(phi: np.ndarray, coarse: np.ndarray, origin: float, period: int,
           ) -> tuple[np.ndarray, np.ndarray]:
    """Projector coordinate from phase ``phi`` and the absolute ``coarse`` coordinate (NaN
    where unknown): the period index is the one that brings the phase coordinate nearest to
    the coarse one. Returns (coordinate, |coordinate − coarse|), float32."""
    frac = phi.astype(np.float64) / (2 * np.pi)
    with np.errstate(invalid="ignore"):
        m = np.round((coarse - origin) / period - frac)
        u = origin + period * (m + frac)
        return u.astype(np.float32), np.abs(u - coarse).astype(np.float32)


def make_gray_phase(settings: dict[str, Any] | None = None, context: Any = None) -> GrayPhaseCode:
    """Backend factory: ``settings`` validated against :data:`SETTINGS_SCHEMA`."""
    s = {name: spec.default for name, spec in SETTINGS_SCHEMA.items()}
    s.update(settings or {})
    return GrayPhaseCode(**s)
