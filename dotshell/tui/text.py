"""How device status and paths read on screen."""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

from dotshell.server.describe import short_path


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
            text = "×".join(map(str, value)) if isinstance(value, (list, tuple)) else value
            parts.append(f"{key.replace('_', ' ')} {text}")
    return " · ".join(parts)


@functools.lru_cache(maxsize=256)
def shown_path(path: str | Path) -> str:
    """:func:`~dotshell.server.describe.short_path`, remembered: it resolves the path and the
    working directory on disk (system calls that, in a busy process, also wait for the
    interpreter lock), and the panels draw the same few paths — the run, the output directory,
    the profile — on every progress message. The TUI never changes its working directory."""
    return short_path(path)


def copy_text(app: Any, text: str, what: str) -> None:
    """Put ``text`` on the clipboard with Textual's :meth:`~textual.app.App.copy_to_clipboard`
    (OSC 52: the terminal's clipboard where the terminal allows it; tmux needs
    ``set -g set-clipboard on``) and say what was copied."""
    app.copy_to_clipboard(text)
    app.notify(f"copied {what} ({len(text)} characters; OSC 52: the terminal must allow it)",
               timeout=4)
