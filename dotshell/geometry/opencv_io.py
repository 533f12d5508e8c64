"""Rig calibrations in OpenCV FileStorage files (YAML ``.yml``/``.yaml`` or XML ``.xml``).

Key names (all matrices ``opencv-matrix``; lengths in mm, pixel quantities in pixels):

* ``Kc`` (3x3), ``kc`` (5x1) — camera intrinsics and distortion (k1, k2, p1, p2, k3), or any
  of OpenCV's longer models (8, 12 or 14 terms: rational k4–k6, thin prism s1–s4; tilted τx, τy
  are refused unless zero, see :func:`dotshell.geometry.lens.distortion`);
* ``Kp``, ``kp`` — projector intrinsics and distortion;
* ``Rp`` (3x3), ``Tp`` (3x1) — camera frame → projector frame, ``X_p = Rp X_c + Tp``;
* ``frameWidth``, ``frameHeight`` — camera image size; ``screenResX``, ``screenResY`` —
  projector size;
* ``cam_error``, ``proj_error``, ``stereo_error`` — RMS reprojection errors (pixels);
* ``axis_point``, ``axis_direction`` (3x1, optional) — dotshell's turntable axis in the camera
  frame (see :mod:`dotshell.geometry.calibration`).

These are the names SLStudio writes in its ``calibration.xml``, so its files read as they are;
dotshell writes the same names plus the turntable axis. A file without a turntable axis (a rig
without a turntable) gets a placeholder axis — the camera's −y axis through the point 1 m in
front of the camera — and ``source`` says so; single-view reconstruction in the camera frame
does not use it, but turntable scans need a measured axis.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from dotshell.errors import CalibrationError
from dotshell.geometry.calibration import (PLACEHOLDER_AXIS_DIRECTION, PLACEHOLDER_AXIS_POINT,
                                           RigCalibration)
from dotshell.geometry.lens import (DISTORTION_TERMS, OPENCV_DISTORTION_LENGTHS, Lens,
                                   distortion)

OPENCV_SUFFIXES = (".xml", ".yml", ".yaml")
_RMS_KEYS = {"cam_error": "camera", "proj_error": "projector", "stereo_error": "stereo"}


def is_opencv_file(path: Path | str) -> bool:
    """Whether ``path`` names an OpenCV FileStorage file (by its suffix)."""
    return Path(path).suffix.lower() in OPENCV_SUFFIXES


def _optional_matrix(fs: cv2.FileStorage, key: str, shape: tuple[int, ...], where: str
                     ) -> np.ndarray | None:
    return None if fs.getNode(key).empty() else _matrix(fs, key, shape, where)


def _matrix(fs: cv2.FileStorage, key: str, shape: tuple[int, ...], where: str) -> np.ndarray:
    node = fs.getNode(key)
    if node.empty():
        raise CalibrationError(f"{where}: OpenCV calibration has no {key!r} entry; it needs "
                               "Kc, kc, Kp, kp, Rp, Tp, frameWidth, frameHeight, screenResX "
                               "and screenResY.")
    if not _whole_matrix(node):  # OpenCV's mat() overruns memory on a malformed matrix node
        raise CalibrationError(f"{where}: {key!r} is not a whole opencv-matrix (rows, cols, dt "
                               "and rows x cols numbers in data); save the file again with "
                               "cv::FileStorage.")
    m = node.mat()
    if m is None or m.size != int(np.prod(shape)):
        raise CalibrationError(f"{where}: {key!r} must be a {'x'.join(map(str, shape))} matrix, "
                               f"found {None if m is None else m.shape}.")
    return np.asarray(m, np.float64).reshape(shape)


def _whole_matrix(node: cv2.FileNode) -> bool:
    """``node`` is an opencv-matrix whose data has rows x cols numbers of one known type."""
    if not node.isMap():
        return False
    rows, cols, dt, data = (node.getNode(k) for k in ("rows", "cols", "dt", "data"))
    if not (rows.isInt() and cols.isInt() and dt.isString() and data.isSeq()):
        return False
    n = int(rows.real()) * int(cols.real())
    return (dt.string() in ("d", "f", "i", "u", "s", "w", "c") and 0 < n <= 16 and data.size() == n
            and all(data.at(i).isReal() or data.at(i).isInt() for i in range(n)))


def _distortion(fs: cv2.FileStorage, key: str, where: str) -> np.ndarray:
    """A distortion vector of any of OpenCV's lengths, checked (terms named when refused)."""
    node = fs.getNode(key)
    rows, cols = (node.getNode(k) for k in ("rows", "cols")) if node.isMap() else (None, None)
    size = 5  # a missing or malformed entry: _matrix says what is wrong
    if rows is not None and cols is not None and rows.isInt() and cols.isInt():
        size = int(rows.real()) * int(cols.real())
    if size not in OPENCV_DISTORTION_LENGTHS:
        raise CalibrationError(f"{where}: {key!r} has {size} distortion terms; OpenCV's models "
                               f"have 4, 5, 8, 12 or 14 ({', '.join(DISTORTION_TERMS)}).")
    d = _matrix(fs, key, (size,), where)
    try:
        return distortion(d)
    except ValueError as exc:
        raise CalibrationError(f"{where}: {key!r}: {exc}.") from None


def _int(fs: cv2.FileStorage, key: str, where: str) -> int:
    node = fs.getNode(key)
    if node.empty() or (not node.isReal() and not node.isInt()):
        raise CalibrationError(f"{where}: OpenCV calibration has no number {key!r} (the image "
                               "size of the camera or projector in pixels).")
    return int(round(node.real()))


def read_opencv_calibration(path: Path | str) -> RigCalibration:
    """A :class:`RigCalibration` from an OpenCV FileStorage file (SLStudio's or dotshell's)."""
    path = Path(path)
    where = str(path)
    if path.exists() and not path.is_file():
        raise CalibrationError(f"calibration file {path} is not a regular file (a device, FIFO "
                               "or socket); give an OpenCV .yml/.xml file.")
    if not path.is_file():
        raise CalibrationError(f"calibration file {path} does not exist.")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError, UnicodeDecodeError) as exc:  # OpenCV's parser errors
        why = exc.err if isinstance(exc, cv2.error) else exc.__cause__ or exc
        raise CalibrationError(f"{where}: not a readable OpenCV FileStorage file ({why}). Save "
                               "it again with cv::FileStorage, or give a calibration.json.") from None
    if not fs.isOpened():
        raise CalibrationError(f"{where}: not a readable OpenCV FileStorage file.")
    try:
        camera = Lens(_matrix(fs, "Kc", (3, 3), where), _distortion(fs, "kc", where),
                      _int(fs, "frameWidth", where), _int(fs, "frameHeight", where))
        projector = Lens(_matrix(fs, "Kp", (3, 3), where), _distortion(fs, "kp", where),
                         _int(fs, "screenResX", where), _int(fs, "screenResY", where))
        R = _matrix(fs, "Rp", (3, 3), where)
        T = _matrix(fs, "Tp", (3,), where)
        point = _optional_matrix(fs, "axis_point", (3,), where)
        direction = _optional_matrix(fs, "axis_direction", (3,), where)
        rms = {}
        for key, name in _RMS_KEYS.items():
            node = fs.getNode(key)
            if not node.empty():
                rms[name] = float(node.real())
    except (cv2.error, SystemError, UnicodeDecodeError) as exc:  # a node of the wrong kind
        why = exc.err if isinstance(exc, cv2.error) else exc.__cause__ or exc
        raise CalibrationError(f"{where}: an entry is not what an OpenCV calibration holds "
                               f"({why}). Save it again with cv::FileStorage, or give a "
                               "calibration.json.") from None
    finally:
        fs.release()
    source = where
    measured = point is not None and direction is not None
    if point is None or direction is None:
        point = np.asarray(PLACEHOLDER_AXIS_POINT, float)
        direction = np.asarray(PLACEHOLDER_AXIS_DIRECTION, float)
        source = f"{where} (no turntable axis: placeholder)"
    calib = RigCalibration(camera, projector, R, T, point, direction, source=source,
                           rms=rms or None, axis_measured=measured)
    problem = calib.problem()
    if problem:
        raise CalibrationError(f"{where}: {problem}. Re-solve the calibration or restore the "
                               "file.")
    return calib


def write_opencv_calibration(calib: RigCalibration, path: Path | str) -> Path:
    """Write ``calib`` as an OpenCV FileStorage file (format from the suffix: .xml or .yml)."""
    path = Path(path)
    if not is_opencv_file(path):
        raise CalibrationError(f"{path}: an OpenCV calibration file must end in .xml, .yml or "
                               ".yaml.")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
    try:
        fs.write("Kc", calib.camera.K)
        fs.write("kc", calib.camera.dist.reshape(-1, 1))
        fs.write("Kp", calib.projector.K)
        fs.write("kp", calib.projector.dist.reshape(-1, 1))
        fs.write("Rp", calib.R)
        fs.write("Tp", calib.T.reshape(3, 1))
        if calib.axis_measured:
            fs.write("axis_point", calib.axis_point.reshape(3, 1))
            fs.write("axis_direction", calib.axis_direction.reshape(3, 1))
        for key, name in _RMS_KEYS.items():
            value = (calib.rms or {}).get(name)
            if isinstance(value, (int, float)):
                fs.write(key, float(value))
        fs.write("frameWidth", int(calib.camera.width))
        fs.write("frameHeight", int(calib.camera.height))
        fs.write("screenResX", int(calib.projector.width))
        fs.write("screenResY", int(calib.projector.height))
    finally:
        fs.release()
    tmp.replace(path)
    return path


def load_any_calibration(path: Path | str) -> RigCalibration:
    """A calibration from ``calibration.json`` (dotshell) or an OpenCV ``.xml``/``.yml`` file."""
    if is_opencv_file(path):
        return read_opencv_calibration(path)
    return RigCalibration.load(Path(path))
