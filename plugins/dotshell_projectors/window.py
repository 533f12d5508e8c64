"""A projector as a fullscreen window on a named screen (PCs running a desktop), with pyglet.

Optional extra: ``pip install 'dotshell[window]'`` (pyglet). The window opens fullscreen on the
screen chosen by ``screen`` (an index in pyglet's screen list, or a part of its name), shows
each pattern as a texture drawn 1:1 and flips with vsync, so a pattern is complete from the
refresh after ``show()`` returns; the display chain behind it (compositor, projector input lag)
is measured by ``dotshell check PROFILE --connect --latency``.

pyglet API (pyglet 2.x documentation): ``pyglet.display.get_display().get_screens()``,
``pyglet.window.Window(fullscreen=True, screen=..., vsync=True)``, ``pyglet.image.ImageData``
with a negative pitch for top-down rows.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from dotshell.errors import DeviceError
from dotshell.settings import Setting

SETTINGS_SCHEMA: dict[str, Setting] = {
    "screen": Setting("str", "1", "the projector's screen: an index in the screen list (0 = "
                      "primary) or a part of its name"),
    "vsync": Setting("bool", True, "flip on the vertical blank (no tearing)"),
}


def _pyglet():
    try:
        import pyglet
    except ImportError:
        raise DeviceError("window projector: pyglet is not installed; pip install "
                          "'dotshell[window]' (or use the framebuffer backend on a PC without "
                          "a desktop).") from None
    return pyglet


def _screens(pyglet) -> list[Any]:
    get_display = getattr(pyglet, "display", None)
    display = (get_display.get_display() if get_display is not None
               else pyglet.canvas.get_display())
    return list(display.get_screens())


def pick_screen(screens: list[Any], wanted: str) -> Any:
    """The screen named by ``wanted``: an index, or a part of a screen's name."""
    if wanted.isdigit() and int(wanted) < len(screens):
        return screens[int(wanted)]
    for s in screens:
        name = getattr(s, "get_device_name", lambda s=s: str(s))()
        if wanted.lower() in str(name).lower():
            return s
    names = ", ".join(f"{i}: {getattr(s, 'get_device_name', lambda s=s: str(s))()} "
                      f"{s.width}x{s.height}" for i, s in enumerate(screens))
    raise DeviceError(f"window projector: no screen {wanted!r}; the screens are {names}.")


class WindowProjector:
    """Projector: a fullscreen pyglet window."""

    def __init__(self, settings: dict[str, Any]) -> None:
        self.settings = settings
        self.window: Any = None
        self.size: tuple[int, int] = (0, 0)
        self.image: Any = None
        self.last_shown: tuple[str, int] = ("", -1)

    @property
    def resolution(self) -> tuple[int, int]:
        return self.size

    def connect(self) -> None:
        pyglet = _pyglet()
        try:
            screen = pick_screen(_screens(pyglet), self.settings["screen"])
            self.window = pyglet.window.Window(fullscreen=True, screen=screen,
                                               vsync=self.settings["vsync"])
        except DeviceError:
            raise
        except Exception as exc:  # no X server, no GL
            raise DeviceError(f"window projector: cannot open a fullscreen window ({exc}); is "
                              "a desktop session running (DISPLAY set)? Without one use the "
                              "framebuffer backend.") from None
        self.window.set_mouse_visible(False)
        self.size = (self.window.width, self.window.height)
        w, h = self.size
        self.show(np.zeros((h, w), np.uint8), "black")

    def close(self) -> None:
        if self.window is not None:
            try:
                self.window.close()
            except Exception:  # closing must not raise
                pass
            self.window = None

    def show(self, pattern: np.ndarray, name: str = "", index: int = -1) -> None:
        if self.window is None:
            raise DeviceError("window projector: not connected; connect the rig first.")
        p = np.ascontiguousarray(pattern)
        w, h = self.size
        if p.shape != (h, w) or p.dtype != np.uint8:
            raise DeviceError(f"window projector: pattern must be uint8 of shape ({h}, {w}), "
                              f"got {p.dtype} {p.shape}.")
        pyglet = _pyglet()
        self.image = pyglet.image.ImageData(w, h, "L", p.tobytes(), pitch=-w)
        win = self.window
        win.switch_to()
        win.dispatch_events()
        win.clear()
        self.image.blit(0, 0)
        win.flip()
        self.last_shown = (name, index)

    def status(self) -> dict[str, Any]:
        name, index = self.last_shown
        return {"connected": self.window is not None, "resolution": list(self.size),
                "screen": self.settings["screen"], "pattern": name, "pattern_index": index}
