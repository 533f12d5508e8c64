"""A planar calibration target for the simulator: a checkerboard or ChArUco board.

The board is a flat, matte, printed plane of finite size with a white margin of one square
around the squares. Its print is a binary texture (white
and black cells); it is put into the scene as two shapes sharing the plane — one hit where
the texture is white (``target-white`` material), one where it is black (``target-black``) —
so the renderer's per-material shading gives the printed albedo with exact cell edges.

Board frame (mm): origin at the board's top-left outer corner, x along the columns of squares,
y along the rows, z into the board (OpenCV's convention; the print faces −z). The inner corner
between squares (i, j) and (i + 1, j + 1) is at ((i + 1)·s, (j + 1)·s, 0).

A *pose* places the board in the sample frame (it turns with the stage): at rotation
``[0, 0, 0]`` the board stands upright facing the camera at stage angle 0 (board x → sample
+y, board y → sample −z, print facing sample +x, towards the camera); ``rotation_deg =
[roll, tilt, pan]`` then rotates it about the sample x, y and z axes, in that order, and
``centre_mm`` is where the board's centre goes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from dotshell_sim.scene import Material, StagedScene

TARGET_WHITE = Material("target-white", albedo=0.80)
TARGET_BLACK = Material("target-black", albedo=0.05)

#: Board axes at rotation [0, 0, 0], as columns in the sample frame.
UPRIGHT = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])

_TEXELS_PER_SQUARE = 60  # ChArUco print resolution (marker bits fall on whole texels)


def _rot(axis: int, degrees: float) -> np.ndarray:
    a = np.deg2rad(degrees)
    c, s = np.cos(a), np.sin(a)
    i, j = [k for k in range(3) if k != axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def board_rotation(rotation_deg: tuple[float, float, float]) -> np.ndarray:
    """3x3 board → sample rotation for ``[roll, tilt, pan]`` degrees."""
    roll, tilt, pan = rotation_deg
    return _rot(2, pan) @ _rot(1, tilt) @ _rot(0, roll) @ UPRIGHT


def board_to_sample(board: dict[str, Any], pose: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) with ``X_sample = R @ X_board + t`` for a pose ``{rotation_deg, centre_mm}``."""
    R = board_rotation(tuple(pose.get("rotation_deg", (0.0, 0.0, 0.0))))
    s = board["square_mm"]
    centre_board = np.array([board["columns"] * s / 2, board["rows"] * s / 2, 0.0])
    t = np.asarray(pose.get("centre_mm", (0.0, 0.0, 0.0)), float) - R @ centre_board
    return R, t


def print_texture(board: dict[str, Any]) -> tuple[np.ndarray, float, float]:
    """The printed sheet: binary texture (rows, cols) bool (True = white), its texel size (mm)
    and the white margin around the squares (mm; one square, as printed boards have)."""
    cols, rows, s = board["columns"], board["rows"], board["square_mm"]
    if board["kind"] == "checkerboard":
        j, i = np.mgrid[0:rows + 2, 0:cols + 2]
        squares = (i + j) % 2 == 0  # the top-left square is black (OpenCV's printed boards)
        ring = (i == 0) | (j == 0) | (i == cols + 1) | (j == rows + 1)
        return squares | ring, s, s
    aruco = cv2.aruco
    dictionary = aruco.getPredefinedDictionary(getattr(aruco, board["dictionary"]))
    cb = aruco.CharucoBoard((cols, rows), s, board["marker_mm"], dictionary)
    n = _TEXELS_PER_SQUARE
    img = cb.generateImage(((cols + 2) * n, (rows + 2) * n), marginSize=n, borderBits=1)
    return img > 127, s / n, s


class _BoardHits:
    """Ray–board intersection shared by the white and the black half of one board: the scene
    asks both halves with the same ray arrays, so the second asks for the cached answer."""

    def __init__(self, R: np.ndarray, t: np.ndarray, texture: np.ndarray, texel_mm: float,
                 margin_mm: float):
        self.R, self.t = R, t
        self.margin_mm = margin_mm
        self.texture = texture.ravel()
        self.shape = texture.shape
        self.texel_mm = texel_mm
        self._key: tuple | None = None
        self._value: tuple | None = None

    def __call__(self, origins: np.ndarray, dirs: np.ndarray):
        """(t, white, normals): distance (inf = miss), print is white, unit normals."""
        if self._key is not None and self._key[0] is origins and self._key[1] is dirs:
            return self._value
        R = self.R
        if origins.strides[0] == 0:  # one origin for all rays (camera rays): transform once
            o = np.broadcast_to((origins[0] - self.t) @ R, origins.shape)
        else:
            o = (origins - self.t) @ R  # to the board frame: R^T (X - t) as rows
        ox, oy, oz = o[:, 0], o[:, 1], o[:, 2]
        dx = dirs[:, 0] * R[0, 0] + dirs[:, 1] * R[1, 0] + dirs[:, 2] * R[2, 0]
        dy = dirs[:, 0] * R[0, 1] + dirs[:, 1] * R[1, 1] + dirs[:, 2] * R[2, 1]
        dz = dirs[:, 0] * R[0, 2] + dirs[:, 1] * R[1, 2] + dirs[:, 2] * R[2, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -oz / dz
            ix = np.floor((ox + t * dx + self.margin_mm) * (1.0 / self.texel_mm))
            iy = np.floor((oy + t * dy + self.margin_mm) * (1.0 / self.texel_mm))
        h, w = self.shape
        inside = (t > 1e-9) & (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
        white = np.zeros(len(t), bool)
        white[inside] = self.texture[(iy[inside] * w + ix[inside]).astype(np.int64)]
        t = np.where(inside, t, np.inf)
        sign = np.where(dz > 0, -1.0, 1.0)  # face the incoming ray
        normals = sign[:, None] * self.R[:, 2][None, :]
        self._key, self._value = (origins, dirs), (t, white, normals)
        return self._value


@dataclass
class BoardPrint:
    """The part of a planar board where the print is ``white`` (or black): ``intersect`` hits
    only there. Two of these sharing one :class:`_BoardHits` make the whole board."""

    hits: _BoardHits
    white: bool
    material: int = 0

    def intersect(self, origins: np.ndarray, dirs: np.ndarray):
        t, white, normals = self.hits(origins, dirs)
        return np.where(white == self.white, t, np.inf), normals


def with_target(scene: StagedScene, board: dict[str, Any], pose: dict[str, Any]) -> StagedScene:
    """``scene`` plus the board at ``pose`` among the sample shapes (it turns with the stage)."""
    R, t = board_to_sample(board, pose)
    texture, texel, margin = print_texture(board)
    materials = list(scene.materials) + [TARGET_WHITE, TARGET_BLACK]
    white, black = len(materials) - 2, len(materials) - 1
    hits = _BoardHits(R, t, texture, texel, margin)
    shapes = [BoardPrint(hits, True, white), BoardPrint(hits, False, black)]
    return StagedScene(list(scene.sample) + shapes, list(scene.fixed), materials)
