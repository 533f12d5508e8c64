"""How device status reads on screen (pure strings)."""

from __future__ import annotations

from typing import Any


def describe_status(role: str, status: dict[str, Any], projected: str | None = None,
                    compact: bool = False) -> str:
    """One line of a device's live status: angle, exposure, pattern, ... ; errors first.
    ``compact`` keeps only angle, exposure, pattern and on/off."""
    if "error" in status:
        return f"error: {status['error']}"
    parts = []
    if "angle_deg" in status:
        parts.append(f"angle {float(status['angle_deg']):.2f}°")
    if "exposure_ms" in status:
        parts.append(f"exposure {float(status['exposure_ms']):g} ms")
    if role == "projector" and projected:
        parts.append(f"pattern {projected}")
    if "on" in status:
        parts.append("on" if status["on"] else "off")
    shown = {"angle_deg", "exposure_ms", "on", "connected", "simulated"}
    for key, value in ([] if compact else status.items()):
        if key not in shown:
            if isinstance(value, (list, tuple)):
                value = "×".join(map(str, value))
            parts.append(f"{key.replace('_', ' ')} {value}")
    return " · ".join(parts)
