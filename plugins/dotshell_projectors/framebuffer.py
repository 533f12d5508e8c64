"""A projector on a second screen driven through the Linux framebuffer (``/dev/fbN``).

Works on a lab PC with no desktop session: the kernel's fbdev driver scans the framebuffer
memory out to the projector; dotshell writes each pattern into that memory through a memory map.

Geometry comes from sysfs (Linux ``Documentation/ABI/testing/sysfs-class-graphics`` and the
fbdev core, ``drivers/video/fbdev/core/fbsysfs.c``): ``/sys/class/graphics/fbN/`` holds
``virtual_size`` ("W,H"), ``bits_per_pixel``, ``stride`` (bytes per line) and ``modes`` (the
current video mode first, e.g. ``U:1024x768p-60``, visible size and refresh). The pixel layout
for a bit depth is the common little-endian one (32 bpp XRGB8888: bytes B, G, R, X; 24 bpp
BGR888; 16 bpp RGB565; 8 bpp grey) unless ``pixel_format`` says otherwise.

Writes to framebuffer memory show on the next scan-out: there is no vsync here, so a pattern
can tear across one refresh; ``dotshell check PROFILE --connect --latency`` measures the settle
time that covers it.
"""

from __future__ import annotations

import mmap
import os
from pathlib import Path
from typing import Any

import numpy as np

from dotshell.errors import DeviceError
from dotshell.settings import Setting

SETTINGS_SCHEMA: dict[str, Setting] = {
    "device": Setting("str", "/dev/fb1", "framebuffer device of the projector's screen "
                      "(/dev/fb0 is usually the console)"),
    "sysfs_dir": Setting("str", "", "its sysfs directory; empty = /sys/class/graphics/fbN for "
                         "device /dev/fbN"),
    "pixel_format": Setting("str", "auto", "pixel layout in memory; auto = from bits_per_pixel",
                            choices=("auto", "xrgb8888", "bgr888", "rgb565", "gray8")),
}

#: bytes per pixel of each layout
BYTES = {"xrgb8888": 4, "bgr888": 3, "rgb565": 2, "gray8": 1}
_BY_BPP = {32: "xrgb8888", 24: "bgr888", 16: "rgb565", 8: "gray8"}


def encode(gray: np.ndarray, layout: str) -> np.ndarray:
    """Grey levels (h, w) uint8 → the bytes of each pixel (h, w, BYTES[layout]) uint8."""
    g = np.asarray(gray, np.uint8)
    if layout == "gray8":
        return g[..., None]
    if layout == "rgb565":
        g16 = g.astype(np.uint16)
        v = (g16 >> 3) << 11 | (g16 >> 2) << 5 | (g16 >> 3)
        return v.astype("<u2").view(np.uint8).reshape(*g.shape, 2)
    if layout == "bgr888":
        return np.repeat(g[..., None], 3, axis=2)
    out = np.empty((*g.shape, 4), np.uint8)  # xrgb8888: B, G, R, X in memory
    out[..., :3] = g[..., None]
    out[..., 3] = 255
    return out


def decode(pixels: np.ndarray, layout: str) -> np.ndarray:
    """Pixel bytes (h, w, BYTES[layout]) → the light's grey level (h, w) uint8, the mean of R,
    G and B as an RGB projector mixes them (what the panel shows)."""
    if layout == "gray8":
        return pixels[..., 0].copy()
    if layout == "rgb565":
        v = pixels.copy().view("<u2")[..., 0].astype(np.uint32)
        r, g, b = (v >> 11 & 31) * 255 // 31, (v >> 5 & 63) * 255 // 63, (v & 31) * 255 // 31
    else:
        b, g, r = (pixels[..., i].astype(np.uint32) for i in range(3))
    return ((r + g + b + 1) // 3).astype(np.uint8)


class Geometry:
    """What sysfs says about one framebuffer."""

    def __init__(self, sysfs_dir: Path, pixel_format: str) -> None:
        def read(name: str) -> str:
            try:
                return (sysfs_dir / name).read_text().strip()
            except OSError as exc:
                raise DeviceError(f"framebuffer: cannot read {sysfs_dir / name} ({exc}); is "
                                  "the framebuffer driver loaded (ls /sys/class/graphics)?") \
                    from None

        self.virtual = tuple(int(v) for v in read("virtual_size").split(","))
        self.bpp = int(read("bits_per_pixel"))
        self.stride = int(read("stride"))
        self.width, self.height = self.virtual
        self.refresh_hz = 0.0
        try:
            mode = (sysfs_dir / "modes").read_text().split()[0]  # e.g. U:1024x768p-60
            size, _, rate = mode.split(":", 1)[-1].partition("-")
            w, h = size.rstrip("pi").split("x")
            self.width, self.height = int(w), int(h.rstrip("pi"))
            self.refresh_hz = float(rate or 0)
        except (OSError, IndexError, ValueError):
            pass  # no mode list: the virtual size is the screen
        self.layout = _BY_BPP.get(self.bpp) if pixel_format == "auto" else pixel_format
        if self.layout is None:
            raise DeviceError(f"framebuffer: {self.bpp} bits per pixel has no default layout; "
                              "set pixel_format in [projector.settings].")
        if BYTES[self.layout] * 8 != self.bpp:
            raise DeviceError(f"framebuffer: pixel_format {self.layout!r} has "
                              f"{BYTES[self.layout] * 8} bits per pixel but sysfs says "
                              f"{self.bpp}; fix pixel_format.")
        if self.stride < self.width * BYTES[self.layout]:
            raise DeviceError(f"framebuffer: stride {self.stride} bytes is shorter than a line "
                              f"of {self.width} pixels; check {sysfs_dir}.")

    @property
    def size_bytes(self) -> int:
        return self.stride * self.virtual[1]


class FramebufferProjector:
    """Projector: patterns written into a memory-mapped ``/dev/fbN``."""

    def __init__(self, settings: dict[str, Any]) -> None:
        self.settings = settings
        device = Path(settings["device"])
        self.device = device
        self.sysfs = Path(settings["sysfs_dir"] or f"/sys/class/graphics/{device.name}")
        self.geometry = Geometry(self.sysfs, settings["pixel_format"])
        self._fd: int | None = None
        self._map: mmap.mmap | None = None
        self.last_shown: tuple[str, int] = ("", -1)

    @property
    def resolution(self) -> tuple[int, int]:
        return (self.geometry.width, self.geometry.height)

    def connect(self) -> None:
        g = self.geometry
        try:
            self._fd = os.open(self.device, os.O_RDWR)
        except FileNotFoundError:
            raise DeviceError(f"framebuffer: {self.device} does not exist; list the screens "
                              "with ls /dev/fb* and set device.") from None
        except PermissionError:
            raise DeviceError(f"framebuffer: no permission to open {self.device}; add your "
                              "user to the 'video' group (sudo usermod -aG video $USER) and log "
                              "in again.") from None
        try:
            self._map = mmap.mmap(self._fd, g.size_bytes, mmap.MAP_SHARED,
                                  mmap.PROT_READ | mmap.PROT_WRITE)
        except (OSError, ValueError) as exc:
            self.close()
            raise DeviceError(f"framebuffer: cannot map {g.size_bytes} bytes of {self.device} "
                              f"({exc}); does {self.sysfs} describe this device?") from None
        self.show(np.zeros((g.height, g.width), np.uint8), "black")

    def close(self) -> None:
        if self._map is not None:
            self._map.close()
            self._map = None
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def memory(self) -> np.ndarray:
        """The visible screen's pixel bytes (height, width, bytes per pixel), a view into the
        mapped framebuffer."""
        if self._map is None:
            raise DeviceError("framebuffer: not connected; connect the rig first.")
        g = self.geometry
        lines = np.frombuffer(self._map, np.uint8, g.stride * g.height).reshape(g.height,
                                                                                g.stride)
        n = BYTES[g.layout]
        return lines[:, :g.width * n].reshape(g.height, g.width, n)

    def show(self, pattern: np.ndarray, name: str = "", index: int = -1) -> None:
        p = np.asarray(pattern)
        w, h = self.resolution
        if p.shape != (h, w) or p.dtype != np.uint8:
            raise DeviceError(f"framebuffer {self.device}: pattern must be uint8 of shape "
                              f"({h}, {w}), got {p.dtype} {p.shape}.")
        self.memory()[:] = encode(p, self.geometry.layout)
        self.last_shown = (name, index)

    def status(self) -> dict[str, Any]:
        g = self.geometry
        name, index = self.last_shown
        return {"connected": self._map is not None, "device": str(self.device),
                "resolution": [g.width, g.height], "pixel_format": g.layout,
                "refresh_hz": g.refresh_hz, "pattern": name, "pattern_index": index}
