"""The planar target (checkerboard or ChArUco) and finding its corners in an image.

Board frame (mm): origin at the top-left outer corner of the board, x along the columns of
squares, y along the rows, z into the board. Inner corner ``k = j·(columns − 1) + i`` (between
squares (i, j) and (i + 1, j + 1)) is at ((i + 1)·s, (j + 1)·s, 0) — OpenCV's ChArUco corner
numbering, used for checkerboards too.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from dataclasses import asdict, dataclass, replace
from typing import Any, Mapping

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
    def from_settings(cls, s: Mapping[str, Any]) -> Board:
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


#: Detections by image content and board, most recent last (see :func:`detect`).
_DETECTIONS: OrderedDict[tuple[bytes, Board], Detection | None] = OrderedDict()
_MAX_DETECTIONS = 512
_DETECTIONS_LOCK = threading.Lock()  # a server may solve two captures at once


def _image_key(image: np.ndarray) -> bytes:
    """A digest of an image's pixels, shape and type."""
    h = hashlib.blake2b(repr((image.shape, image.dtype.str)).encode(), digest_size=16)
    h.update(np.ascontiguousarray(image).tobytes())
    return h.digest()


def detect(image: np.ndarray, board: Board) -> Detection | None:
    """The board's corners in ``image`` (None when the board is not found).

    The result is kept for the last :data:`_MAX_DETECTIONS` images (by their pixels) and
    boards: solving a capture again in the same process (other settings, a pose left out or
    changed) takes the corners of the unchanged images without searching them again (the
    search and refinement are ~2/3 of a reduced solve); a caller gets its own copy."""
    key = (_image_key(image), board)
    with _DETECTIONS_LOCK:
        known = key in _DETECTIONS
        det = _DETECTIONS.get(key)
        if known:
            _DETECTIONS.move_to_end(key)
    if not known:
        det = _search(image, board)  # outside the lock: the search is the slow part
        with _DETECTIONS_LOCK:
            _DETECTIONS[key] = det
            while len(_DETECTIONS) > _MAX_DETECTIONS:
                _DETECTIONS.popitem(last=False)
    return None if det is None else replace(det, pixels=det.pixels.copy(), ids=det.ids.copy())


def _search(image: np.ndarray, board: Board) -> Detection | None:
    """The board's corners found and refined in ``image`` (None when not found)."""
    img = to_8bit(image)
    if board.kind == "checkerboard":
        flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_NORMALIZE_IMAGE
        found, corners = cv2.findChessboardCornersSB(img, board.inner, flags=flags)
        if not found or corners is None or len(corners) != board.n_corners:
            return None
        px = refine_corners(image, corners.reshape(-1, 2).astype(np.float64), board.inner)
        sharp = cv2.estimateChessboardSharpness(img, board.inner, corners)
        return Detection(px, np.arange(board.n_corners), float(np.ravel(sharp[0])[0]))
    detector = cv2.aruco.CharucoDetector(board.charuco())
    corners, ids, _, _ = detector.detectBoard(img)
    if ids is None or len(ids) < max(6, board.n_corners // 4):
        return None
    return Detection(corners.reshape(-1, 2).astype(np.float64), ids.ravel().astype(np.int64))


#: Corner-refinement window half-size as a fraction of the nearest-corner spacing in the image.
REFINE_WINDOW = 0.3
_REFINE_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-5)


def refine_corners(image: np.ndarray, pixels: np.ndarray,
                   grid: tuple[int, int] | None = None) -> np.ndarray:
    """Corners (N, 2) px refined on the full-depth image.

    ``findChessboardCornersSB`` places corners to ~0.1–0.3 px (it works on an 8-bit copy).
    First ``cv2.cornerSubPix`` (every gradient in the window orthogonal to the vector from the
    corner) brings them to ~0.04 px; then, for a full ``grid`` (inner corners across, down, in
    row order), :func:`fit_corner` fits the blurred two-edge model to each window, which
    measured ~0.01 px on the simulated bench. Windows are ±0.3 × the corner spacing.
    """
    if len(pixels) < 2:
        return pixels
    from scipy.spatial import cKDTree

    d, _ = cKDTree(pixels).query(pixels, k=2)
    half = max(3, int(REFINE_WINDOW * float(np.min(d[:, 1]))))
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    gray = gray.astype(np.float32)
    refined = cv2.cornerSubPix(gray, pixels.astype(np.float32).reshape(-1, 1, 2),
                               (half, half), (-1, -1), _REFINE_CRITERIA)
    out = refined.reshape(-1, 2).astype(np.float64)
    lost = np.linalg.norm(out - pixels, axis=1) > half / 2  # lost the corner: keep SB's
    out[lost] = pixels[lost]
    if grid is None or grid[0] * grid[1] != len(out) or min(grid) < 2:
        return out
    angles = _edge_angles(out, grid)
    for k in range(len(out)):
        fitted = fit_corner(gray, out[k], half, angles[k])
        if fitted is not None:
            out[k] = fitted
    return out


def _edge_angles(pixels: np.ndarray, grid: tuple[int, int]) -> np.ndarray:
    """(N, 2) image directions (rad) of the board's x and y lines at each grid corner."""
    w, h = grid
    P = pixels.reshape(h, w, 2)
    gx, gy = np.gradient(P, axis=1), np.gradient(P, axis=0)
    return np.column_stack([np.arctan2(gx[..., 1], gx[..., 0]).ravel(),
                            np.arctan2(gy[..., 1], gy[..., 0]).ravel()])


def fit_corner(gray: np.ndarray, start: np.ndarray, half: int,
               angles: np.ndarray) -> np.ndarray | None:
    """A corner (px) by fitting ``m + a·erf(d1/√2s)·erf(d2/√2s)`` to the window around
    ``start``: d1, d2 the signed distances (px) to the two edge lines through the corner (free
    directions, starting at ``angles``), s the edge blur (px), m and a the mean level and
    contrast. None when the window leaves the image or the fit does not settle near ``start``.
    """
    from scipy.optimize import leastsq
    from scipy.special import erf

    x0, y0 = int(round(start[0])), int(round(start[1]))
    h, w = gray.shape
    if x0 - half < 0 or y0 - half < 0 or x0 + half >= w or y0 + half >= h:
        return None
    win = gray[y0 - half:y0 + half + 1, x0 - half:x0 + half + 1].astype(np.float64).ravel()
    ys, xs = np.mgrid[-half:half + 1, -half:half + 1].astype(np.float64)
    xs, ys = (xs + x0 - start[0]).ravel(), (ys + y0 - start[1]).ravel()
    lo, hi = np.percentile(win, [5, 95])

    last: list = [None, None]  # the parameters of the newest model evaluation, and its terms

    def edges(q: np.ndarray):
        """The model's terms at ``q``; MINPACK asks for the Jacobian at the point whose
        residuals it has just evaluated, so the newest evaluation is kept."""
        key = q.tobytes()
        if last[0] == key:
            return last[1]
        dx, dy, t1, t2, _, _, s = q
        X, Y = xs - dx, ys - dy
        k = 1.0 / (np.sqrt(2.0) * max(abs(s), 0.05))
        c1, s1, c2, s2 = np.cos(t1), np.sin(t1), np.cos(t2), np.sin(t2)
        d1, d2 = (c1 * Y - s1 * X) * k, (c2 * Y - s2 * X) * k
        last[:] = key, (X, Y, k, (c1, s1, d1, erf(d1)), (c2, s2, d2, erf(d2)))
        return last[1]

    def residuals(q: np.ndarray) -> np.ndarray:
        _, _, _, (_, _, _, e1), (_, _, _, e2) = edges(q)
        return q[4] + q[5] * e1 * e2 - win

    def jacobian(q: np.ndarray) -> np.ndarray:
        """∂residuals/∂q, analytic (d erf(z)/dz = 2/√π·exp(−z²)): half the solve's CPU of
        scipy's finite differences, which evaluate the model once more per parameter."""
        a, s = q[5], q[6]
        X, Y, k, (c1, s1, d1, e1), (c2, s2, d2, e2) = edges(q)
        g1 = a * e2 * (2.0 / np.sqrt(np.pi)) * np.exp(-d1 * d1)  # ∂r/∂d1
        g2 = a * e1 * (2.0 / np.sqrt(np.pi)) * np.exp(-d2 * d2)  # ∂r/∂d2
        ds = -np.sign(s) / abs(s) if abs(s) > 0.05 else 0.0    # ∂d/∂s = d · ds
        return np.column_stack([
            (g1 * s1 + g2 * s2) * k, -(g1 * c1 + g2 * c2) * k,
            -g1 * (s1 * Y + c1 * X) * k, -g2 * (s2 * Y + c2 * X) * k,
            np.ones_like(d1), e1 * e2, (g1 * d1 + g2 * d2) * ds])

    starts = [np.array([0.0, 0.0, angles[0], angles[1], (lo + hi) / 2, sign * (hi - lo) / 2, 0.8])
              for sign in (1.0, -1.0)]
    q0 = min(starts, key=lambda q: float(np.sum(residuals(q) ** 2)))  # which squares are white
    # MINPACK's Levenberg–Marquardt as least_squares(method="lm") runs it (gtol 1e-8, at most
    # 100 evaluations per parameter, variables scaled by the Jacobian's columns), without that
    # wrapper's per-evaluation bookkeeping, which cost more than the 7-parameter model itself
    # (a board has ~100 corners, each fit ~20 evaluations)
    q, _, _, _, status = leastsq(residuals, q0, Dfun=jacobian, full_output=True, xtol=1e-10,
                                 ftol=1e-10, gtol=1e-8, maxfev=100 * len(q0))
    shift = q[:2]
    if not (status in (1, 2, 3, 4) and np.all(np.isfinite(shift)) and np.hypot(*shift) < 1.0):
        return None
    return start + shift


def flipped(det: Detection, board: Board) -> Detection:
    """The same detection with the corner order rotated by 180° (a checkerboard's symmetry)."""
    return Detection(det.pixels[::-1].copy(), det.ids.copy(), det.sharpness_px)


def other_count(image: np.ndarray, board: Board) -> Board | None:
    """A checkerboard one square more or fewer each way than ``board`` found in ``image``
    (the counts given as inner corners, or as squares where corners were meant); ``None``
    when neither is there or the target is not a checkerboard."""
    if board.kind != "checkerboard":
        return None
    for step in (1, -1):
        other = replace(board, columns=board.columns + step, rows=board.rows + step)
        if min(other.columns, other.rows) >= 3 and detect(image, other) is not None:
            return other
    return None
