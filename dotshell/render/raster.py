"""A small software renderer for the run's 3-D previews: point clouds and triangle surfaces drawn
with numpy and OpenCV into a BGR image, looked at along one direction (orthographic).

Why not pyvista/VTK, which drew them before: a preview is one picture, and importing pyvista's
plotting (with VTK's rendering and matplotlib) cost 1-2 s of CPU, and opening an off-screen
OpenGL context ~0.3 s more, in every ``reconstruct``, scan and ``mesh`` (docs/performance.md,
issue 32); drawing 300 k points or a few thousand triangles here takes ~0.1 s and needs no
OpenGL. Points are drawn as squares of ``size`` pixels, the nearest point winning each pixel;
triangles by the painter's algorithm (far to near, faces turned away culled), shaded by the
angle between their normal and the viewing direction, with their edges drawn over them.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

#: colours (BGR, 0-255)
BLACK = (0, 0, 0)
WHITE = (255, 255, 255)
#: Moreland's cool-warm diverging map by its end and middle points (sRGB): blue, grey, red
COOLWARM_RGB = np.array([(59, 76, 192), (221, 221, 221), (180, 4, 38)], np.float64)
FONT = cv2.FONT_HERSHEY_SIMPLEX


def colormap(name: str) -> np.ndarray:
    """(256, 3) uint8 BGR lookup table of ``name``: ``viridis`` (OpenCV's) or ``coolwarm``."""
    if name == "viridis":
        ramp = np.arange(256, dtype=np.uint8).reshape(256, 1)
        return cv2.applyColorMap(ramp, cv2.COLORMAP_VIRIDIS).reshape(256, 3)
    if name == "coolwarm":
        t = np.linspace(0.0, 2.0, 256)
        rgb = np.column_stack([np.interp(t, [0, 1, 2], COOLWARM_RGB[:, c]) for c in range(3)])
        return np.round(rgb[:, ::-1]).astype(np.uint8)
    raise ValueError(f"unknown colour map {name!r}; known: viridis, coolwarm")


def scalar_colours(values: np.ndarray, clim: tuple[float, float], cmap: str) -> np.ndarray:
    """(N, 3) uint8 BGR colours of ``values`` over ``clim`` (clipped at its ends)."""
    lo, hi = clim
    t = (np.asarray(values, np.float64) - lo) / max(hi - lo, 1e-12)
    return colormap(cmap)[np.clip(np.round(t * 255), 0, 255).astype(np.intp)]


@dataclass(frozen=True)
class Camera:
    """A viewing direction: ``right`` and ``up`` span the picture, ``forward`` points from the
    eye into the scene (unit vectors, sample frame)."""

    right: np.ndarray
    up: np.ndarray
    forward: np.ndarray

    @classmethod
    def looking(cls, forward, up) -> Camera:
        """Looking along ``forward`` with ``up`` (any vector not parallel to it) upwards."""
        f = np.asarray(forward, np.float64)
        f = f / np.linalg.norm(f)
        r = np.cross(f, np.asarray(up, np.float64))
        r /= np.linalg.norm(r)
        return cls(r, np.cross(r, f), f)

    @classmethod
    def iso(cls, azimuth_deg: float = 30.0) -> Camera:
        """From the (+x, +y, +z) diagonal down to the centre, z up, the eye then turned
        ``azimuth_deg`` about z (the view the previews had with pyvista's "iso" camera)."""
        a = np.radians(azimuth_deg)
        c, s = np.cos(a), np.sin(a)
        eye = np.array([c - s, s + c, 1.0])  # (1, 1, 1) turned about z
        return cls.looking(-eye, (0.0, 0.0, 1.0))


class Canvas:
    """A white BGR picture of ``size`` pixels with a plot area for one scene; :meth:`fit`
    chooses the scale so that the given points fill the area."""

    def __init__(self, size: tuple[int, int] = (900, 900), camera: Camera | None = None,
                 right_margin: int = 0) -> None:
        self.width, self.height = size
        self.image = np.full((self.height, self.width, 3), 255, np.uint8)
        self.camera = camera or Camera.iso()
        self.area = (30, 50, self.width - 30 - right_margin, self.height - 60)  # x0 y0 x1 y1
        self.scale = 1.0
        self.centre = np.zeros(2)

    def screen(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) picture coordinates before fitting (mm) and depth along ``forward`` (mm)."""
        p = np.asarray(points, np.float64)
        c = self.camera
        return np.column_stack([p @ c.right, -(p @ c.up)]), p @ c.forward

    def fit(self, points: np.ndarray) -> None:
        """Scale and centre so that ``points`` fill the plot area."""
        xy, _ = self.screen(points)
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        x0, y0, x1, y1 = self.area
        span = np.maximum(hi - lo, 1e-9)
        self.scale = float(min((x1 - x0) / span[0], (y1 - y0) / span[1]))
        self.centre = (lo + hi) / 2

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) pixel coordinates (float) and depth (mm, larger is farther)."""
        xy, depth = self.screen(points)
        x0, y0, x1, y1 = self.area
        return (xy - self.centre) * self.scale + [(x0 + x1) / 2, (y0 + y1) / 2], depth


def draw_points(canvas: Canvas, points: np.ndarray, colours: np.ndarray, size: int = 2) -> None:
    """Squares of ``size`` pixels at ``points`` (N, 3, mm), each pixel showing the nearest."""
    xy, depth = canvas.project(points)
    order = np.argsort(depth, kind="stable")  # nearest first
    ix = np.floor(xy[order, 0]).astype(np.int64)
    iy = np.floor(xy[order, 1]).astype(np.int64)
    w, h = canvas.width, canvas.height
    offsets = [(dx, dy) for dy in range(size) for dx in range(size)]
    px = ix[:, None] + np.array([o[0] for o in offsets])
    py = iy[:, None] + np.array([o[1] for o in offsets])
    inside = (px >= 0) & (px < w) & (py >= 0) & (py < h)
    flat = (py * w + px)[inside]  # point by point, nearest point first
    owner = np.broadcast_to(order[:, None], px.shape)[inside]
    pixels, first = np.unique(flat, return_index=True)  # stable: the nearest point's entry
    canvas.image.reshape(-1, 3)[pixels] = np.asarray(colours, np.uint8)[owner[first]]


def draw_triangles(canvas: Canvas, vertices: np.ndarray, triangles: np.ndarray,
                   colour: tuple[int, int, int], edge: tuple[int, int, int] | None = BLACK,
                   cull: bool = True) -> None:
    """Flat-shaded triangles (outward-oriented, counter-clockwise seen from outside) with their
    edges; with ``cull``, faces turned away from the eye are not drawn."""
    v = np.asarray(vertices, np.float64)
    tri = np.asarray(triangles, np.int64)
    xy, depth = canvas.project(v)
    normal = np.cross(v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]])
    facing = normal @ canvas.camera.forward
    norm = np.maximum(np.linalg.norm(normal, axis=1), 1e-30)
    keep = facing < 0 if cull else np.ones(len(tri), bool)
    shade = 0.35 + 0.65 * np.abs(facing) / norm
    order = np.nonzero(keep)[0]
    order = order[np.argsort(-depth[tri[order]].mean(axis=1), kind="stable")]  # far first
    corners = np.round(xy * 16).astype(np.int32)  # 4 bits of sub-pixel precision
    base = np.asarray(colour, np.float64)
    fills = np.round(shade[:, None] * base).astype(int)
    img = canvas.image
    for i in order:
        poly = corners[tri[i]]
        cv2.fillConvexPoly(img, poly, tuple(int(c) for c in fills[i]), cv2.LINE_AA, 4)
        if edge is not None:
            cv2.polylines(img, [poly], True, edge, 1, cv2.LINE_AA, 4)


def ascii_text(text: str) -> str:
    """``text`` as OpenCV's Hershey fonts can draw it (ASCII; other characters as '?')."""
    return text.encode("ascii", "replace").decode("ascii")


def draw_title(canvas: Canvas, title: str) -> None:
    cv2.putText(canvas.image, ascii_text(title), (12, 28), FONT, 0.6, BLACK, 1, cv2.LINE_AA)


def tick_label(value: float, span: float) -> str:
    """``value`` to 3 significant digits, and 0 where it is rounding noise against the bar's
    ``span`` (the middle of a symmetric range is 0, not 8.77e-10)."""
    if span > 0 and abs(value) < 1e-9 * span:
        value = 0.0
    return f"{value:.3g}"


def draw_colour_bar(canvas: Canvas, clim: tuple[float, float], cmap: str, label: str) -> None:
    """A vertical colour bar at the right edge, ``clim`` at its ends and its middle."""
    lut = colormap(cmap)
    x0, x1 = canvas.width - 95, canvas.width - 70
    y0, y1 = int(canvas.height * 0.2), int(canvas.height * 0.8)
    rows = np.linspace(255, 0, y1 - y0).round().astype(np.intp)  # high values at the top
    canvas.image[y0:y1, x0:x1] = lut[rows][:, None, :]
    cv2.rectangle(canvas.image, (x0, y0), (x1 - 1, y1 - 1), BLACK, 1)
    lo, hi = clim
    for value, y in ((hi, y0), ((lo + hi) / 2, (y0 + y1) // 2), (lo, y1)):
        cv2.putText(canvas.image, tick_label(value, hi - lo), (x1 + 4, y + 5), FONT, 0.45,
                    BLACK, 1, cv2.LINE_AA)
    cv2.putText(canvas.image, ascii_text(label), (x0 - 60, y0 - 12), FONT, 0.45, BLACK, 1,
                cv2.LINE_AA)


def draw_axes(canvas: Canvas, length_px: float = 45.0) -> None:
    """The sample frame's x (red), y (green) and z (blue) axes as seen, at the lower left."""
    origin = np.array([60.0, canvas.height - 45.0])
    c = canvas.camera
    for axis, colour, name in ((0, (0, 0, 220), "x"), (1, (0, 160, 0), "y"), (2, (220, 0, 0), "z")):
        unit = np.zeros(3)
        unit[axis] = 1.0
        tip = origin + length_px * np.array([unit @ c.right, -(unit @ c.up)])
        a, b = tuple(int(round(x)) for x in origin), tuple(int(round(x)) for x in tip)
        cv2.line(canvas.image, a, b, colour, 2, cv2.LINE_AA)
        cv2.putText(canvas.image, name, (b[0] + 3, b[1] + 3), FONT, 0.5, colour, 1, cv2.LINE_AA)
