"""The planar target (checkerboard or ChArUco) and finding its corners in an image.

Board frame (mm): origin at the top-left outer corner of the board, x along the columns of
squares, y along the rows, z into the board. Inner corner ``k = j·(columns − 1) + i`` (between
squares (i, j) and (i + 1, j + 1)) is at ((i + 1)·s, (j + 1)·s, 0) — OpenCV's ChArUco corner
numbering, used for checkerboards too.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import cv2
import numpy as np

from dotshell.errors import CalibrationError


@dataclass(frozen=True)
class Board:
    """A printed planar target.

    Attributes:
        kind: ``"checkerboard"`` or ``"charuco"``.
        columns, rows: squares across and down.
        square_mm: side of a square (mm).
        marker_mm: ArUco marker side (mm, ChArUco only).
        dictionary: cv2.aruco dictionary name (ChArUco only).
    """

    kind: str
    columns: int
    rows: int
    square_mm: float
    marker_mm: float = 0.0
    dictionary: str = "DICT_4X4_50"

    @classmethod
    def from_settings(cls, s: dict[str, Any]) -> "Board":
        return cls(s["target"], s["columns"], s["rows"], s["square_mm"], s["marker_mm"],
                   s["dictionary"])

    @property
    def inner(self) -> tuple[int, int]:
        """Inner corners (across, down)."""
        return (self.columns - 1, self.rows - 1)

    @property
    def n_corners(self) -> int:
        return self.inner[0] * self.inner[1]

    @property
    def centre(self) -> np.ndarray:
        """The board's centre in the board frame (mm)."""
        return np.array([self.columns * self.square_mm / 2, self.rows * self.square_mm / 2, 0.0])

    def object_points(self) -> np.ndarray:
        """All inner corners (N, 3) in the board frame (mm), by corner id."""
        w, h = self.inner
        j, i = np.mgrid[0:h, 0:w]
        s = self.square_mm
        return np.column_stack([(i.ravel() + 1) * s, (j.ravel() + 1) * s, np.zeros(w * h)])

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    def sim_dict(self) -> dict[str, Any]:
        """The board as the simulator's ``place_target`` takes it."""
        return {"kind": self.kind, "columns": self.columns, "rows": self.rows,
                "square_mm": self.square_mm, "marker_mm": self.marker_mm,
                "dictionary": self.dictionary}

    def charuco(self):
        aruco = cv2.aruco
        if not hasattr(aruco, self.dictionary):
            raise CalibrationError(f"[calibrate] dictionary = {self.dictionary!r} is not a "
                                   "cv2.aruco dictionary; use e.g. DICT_4X4_50 or DICT_5X5_100.")
        d = aruco.getPredefinedDictionary(getattr(aruco, self.dictionary))
        return aruco.CharucoBoard((self.columns, self.rows), self.square_mm, self.marker_mm, d)


@dataclass
class Detection:
    """Corners found in one image: ``pixels`` (N, 2) and their corner ``ids`` (N,)."""

    pixels: np.ndarray
    ids: np.ndarray
    sharpness_px: float = float("nan")


def to_8bit(image: np.ndarray) -> np.ndarray:
    """Stretch a frame (any depth) to uint8 between its 0.5 and 99.5 percentiles."""
    if image.dtype == np.uint8:
        return image
    f = image.astype(np.float32)
    lo, hi = np.percentile(f, [0.5, 99.5])
    return np.clip((f - lo) / max(float(hi - lo), 1e-6) * 255.0, 0, 255).astype(np.uint8)


def detect(image: np.ndarray, board: Board) -> Detection | None:
    """The board's corners in ``image`` (None when the board is not found)."""
    img = to_8bit(image)
    if board.kind == "checkerboard":
        flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_NORMALIZE_IMAGE
        found, corners = cv2.findChessboardCornersSB(img, board.inner, flags=flags)
        if not found or corners is None or len(corners) != board.n_corners:
            return None
        px = corners.reshape(-1, 2).astype(np.float64)
        sharp = cv2.estimateChessboardSharpness(img, board.inner, corners)
        return Detection(px, np.arange(board.n_corners), float(sharp[0][0]))
    detector = cv2.aruco.CharucoDetector(board.charuco())
    corners, ids, _, _ = detector.detectBoard(img)
    if ids is None or len(ids) < max(6, board.n_corners // 4):
        return None
    return Detection(corners.reshape(-1, 2).astype(np.float64), ids.ravel().astype(np.int64))


def flipped(det: Detection, board: Board) -> Detection:
    """The same detection with the corner order rotated by 180° (a checkerboard's symmetry)."""
    return Detection(det.pixels[::-1].copy(), det.ids.copy(), det.sharpness_px)
