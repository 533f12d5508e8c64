"""Views an operator marked **lost**: their frames are bad (cut, damaged, blurred) and cannot
be re-captured, so the run is finished from the other views (``dotshell lose-view``).

A lost view keeps its manifest entry — ``index``, ``angle_deg``, ``frames`` on disk and
``complete`` stay true of its capture, and its frames stay on disk — with ``lost``: ``reason``
(the operator's words), ``marked`` (ISO time) and ``frames_on_disk`` (whole pages when it was
marked). Processing skips it, ``resume`` does not capture it again unless asked with
``--view N`` (which captures it whole and clears the mark), and a run whose every view is
captured or lost is ``completed``, its ``reason`` naming the lost views.
"""

from __future__ import annotations

from typing import Any


def is_lost(view: dict[str, Any]) -> bool:
    """Whether a manifest view entry is marked lost."""
    return bool(view.get("lost"))


def lost_views(manifest: dict[str, Any]) -> list[dict[str, Any]]:
    """The manifest's lost views: ``view``, ``angle_deg`` (commanded, degrees), ``reason``."""
    return [{"view": v["index"], "angle_deg": v["angle_deg"], "reason": v["lost"]["reason"]}
            for v in manifest["views"] if is_lost(v)]


def usable(view: dict[str, Any]) -> bool:
    """A view processing reads: captured whole and not marked lost."""
    return bool(view.get("complete")) and not is_lost(view)


def finished(view: dict[str, Any]) -> bool:
    """A view the run needs nothing more of: captured whole, or marked lost."""
    return bool(view.get("complete")) or is_lost(view)


def lost_reason(manifest: dict[str, Any]) -> str:
    """The run's ``reason`` for a completed run with lost views ("" without any)."""
    lost = lost_views(manifest)
    if not lost:
        return ""
    n = len(manifest["views"])
    named = "; ".join(f"view {v['view']} ({v['angle_deg']:g}°): {v['reason']}" for v in lost)
    return (f"completed from {n - len(lost)} of {n} views; lost: {named} "
            "(`dotshell resume RUN --view N` re-captures a lost view)")


def check_lost_entry(entry: Any) -> str | None:
    """What is wrong with a view's ``lost`` entry, or None (absent or well formed)."""
    if entry is None:
        return None
    if not isinstance(entry, dict) or not isinstance(entry.get("reason"), str) \
            or not entry["reason"].strip():
        return "lost must be an object with a non-empty 'reason'"
    return None
