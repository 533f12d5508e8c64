"""How well one view decoded: the decoded share of the image and an estimate of its wrong codes,
the *neighbour reversals* — one definition for ``dotshell decode``, a scan's, a resume's and a
reconstruction's views and ``reconstruct --captures`` (docs/codings.md#decode-quality).

On a continuous surface a projector coordinate map (column or row) is monotonic across the
stripes: seen along the image axis in which it changes, each step between adjacent decoded
pixels goes the same way. A step back by more than :data:`REVERSAL_STEP_PX` projector pixels
marks a wrong code (or a true occlusion boundary, hence an estimate). Per map:

* the **stripe axis** is the image axis (x or y) whose mean step between adjacent decoded pixels
  is the larger in magnitude, its **direction** that step's sign. The steps are summed as
  integers of 1/256 projector px (the same sum in any order, on any number of threads). A sum
  of steps telescopes along a run of decoded pixels, so an isolated wrong code (one step out,
  one back) adds nothing to it;
* the map's **reversals** are the steps along the stripe axis of more than
  :data:`REVERSAL_STEP_PX` against the direction.

A view's ``reversals`` is the column map's plus the row map's; ``reversals_pct`` their share of
the decoded pixels. One compiled pass over each map counts both axes
(:mod:`dotshell.pipeline.reversal_pass`; a few ms at 1280×1024, split across the cores;
docs/performance.md). This module itself loads no numpy or numba: front ends read its notes
and thresholds.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # numpy and the compiled pass load with the first view measured
    import numpy as np

    from dotshell.coding import Correspondence

#: Adjacent decoded pixels whose coordinate steps back by more than this (projector px) against
#: the map's direction count as a reversal.
REVERSAL_STEP_PX = 1.5
#: A view's decode loss (other than shadow) of at least this share of the image (%), or shadow
#: when less than this share decoded, gets its meaning and fix printed (:func:`view_notes`).
NOTE_SHARE_PCT = 5.0
#: Reversals of at least this share of the decoded pixels (%) get their meaning and fix printed.
NOTE_REVERSALS_PCT = 1.0
#: What many reversals mean and what would fix them (printed as a loss's note is).
WRONG_CODES = (
    "adjacent decoded pixels step back across the stripes, each a likely wrong code (or an "
    "occlusion edge, where the reversals follow the object's outline): global light "
    "(inter-reflections, subsurface scattering) or blur flipping bits, or the sample moving "
    "during the view. Where classification = \"contrast\" is set, decode with \"adaptive\" "
    "(the gray code's default) or \"robust\"; check focus; keep the stage settled while a view "
    "is captured; on translucent samples capture with the analyzer (PDI)")
#: Losses a view is checked for (:func:`view_notes`), in pipeline order: those with a meaning
#: and fix in :data:`~dotshell.pipeline.reconstruct.LOSSES`.
_DECODE_LOSSES = ("low_contrast", "uncertain", "out_of_range", "row_rejected")
#: Per axis, the four numbers :func:`~dotshell.pipeline.reversal_pass.step_counts` counts:
#: pairs, summed step, steps up, steps back.
_PAIRS, _SUM, _UP, _DOWN = range(4)


def view_quality(corr: Correspondence) -> dict[str, Any]:
    """The view's ``decoded_pct`` (decoded pixels, % of the image), ``reversals`` (neighbour
    reversals of the column and row maps, see the module docstring) and ``reversals_pct``
    (% of the decoded pixels)."""
    import numpy as np

    valid = np.ascontiguousarray(corr.valid, np.bool_)
    n = int(np.count_nonzero(valid))
    rev = neighbour_reversals(corr.column, valid)
    if corr.row is not None:
        rev += neighbour_reversals(corr.row, valid)
    return {"decoded_pct": round(100.0 * n / max(valid.size, 1), 2), "reversals": rev,
            "reversals_pct": round(100.0 * rev / max(n, 1), 3)}


def view_notes(stats: dict[str, Any], quality: dict[str, Any]) -> tuple[tuple[str, float], ...]:
    """The problems of a scanned view worth their meaning and fix, as (key, share %): each
    decode or triangulation loss of at least :data:`NOTE_SHARE_PCT` of the image (keys of
    :data:`~dotshell.pipeline.reconstruct.LOSSES`); ``shadow`` only when less than that share
    decoded (around an object the unlit background is shadow); ``reversals`` (share of the
    decoded pixels, :data:`WRONG_CODES`) from :data:`NOTE_REVERSALS_PCT` on. A coding whose
    counts do not hold ``pixels`` gets the reversals' note only."""
    notes: list[tuple[str, float]] = []
    total = int(stats.get("pixels") or 0)
    if total > 0:
        shares = {k: round(100.0 * int(stats.get(k) or 0) / total, 1)
                  for k in ("shadow", *_DECODE_LOSSES)}
        notes = [(k, shares[k]) for k in _DECODE_LOSSES if shares[k] >= NOTE_SHARE_PCT]
        decoded_pct = quality.get("decoded_pct", 100.0 * int(stats.get("decoded", 0)) / total)
        if decoded_pct < NOTE_SHARE_PCT and shares["shadow"] >= NOTE_SHARE_PCT:
            notes.insert(0, ("shadow", shares["shadow"]))
    if quality.get("reversals_pct", 0.0) >= NOTE_REVERSALS_PCT:
        notes.append(("reversals", float(quality["reversals_pct"])))
    return tuple(notes)


def quality_fields(stats: dict[str, Any], quality: dict[str, Any]) -> dict[str, Any]:
    """A view's quality as :class:`~dotshell.events.ViewReconstructed`'s fields (none without
    a quality)."""
    if not quality:
        return {}
    return {"decoded_pct": quality["decoded_pct"], "reversals": quality["reversals"],
            "reversals_pct": quality["reversals_pct"], "notes": view_notes(stats, quality)}


def neighbour_reversals(coord: np.ndarray, valid: np.ndarray) -> int:
    """One map's reversals: steps between adjacent ``valid`` pixels of ``coord`` (projector
    px, float) along its stripe axis that go back by more than :data:`REVERSAL_STEP_PX`
    against its direction (module docstring)."""
    from dotshell.pipeline.reversal_pass import step_counts

    return reversals_of(step_counts(coord, valid, REVERSAL_STEP_PX))


def reversals_of(counts: np.ndarray) -> int:
    """The reversals in :func:`~dotshell.pipeline.reversal_pass.step_counts`' figures: the
    steps back against the direction along the axis of the larger mean step (x on a tie; the
    direction is up on a zero sum)."""
    best_axis, best_slope = 0, -1.0
    for axis in (0, 1):
        pairs = counts[axis, _PAIRS]
        slope = abs(float(counts[axis, _SUM])) / pairs if pairs else 0.0
        if pairs and slope > best_slope:
            best_axis, best_slope = axis, slope
    c = counts[best_axis]
    return int(c[_DOWN] if c[_SUM] >= 0 else c[_UP])
