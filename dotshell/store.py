"""RunStore: one scan's run directory. Every file is written to a temporary name and renamed
(atomic on POSIX), frames are written losslessly (PNG, 8 or 16 bit) as they arrive, and
``events.jsonl`` is appended and flushed per event — a crash loses nothing already written.

Layout (see ``docs/run-directory.md``)::

    <run>/profile.toml  calibration.json  manifest.json  events.jsonl  report.json
    <run>/frames/view_000/000_white.png ...
    <run>/views/view_000.ply   <run>/cloud.ply   <run>/previews/*.png
"""

from __future__ import annotations

import json
import os
import platform
import re
import tempfile

from datetime import datetime
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import tomli_w

from dotshell.errors import RunError

RUN_FORMAT = "dotshell-run/1"


def _process_umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


#: Mode of the files dotshell writes: what the user's umask allows (lab groups can read runs);
#: ``mkstemp`` alone would make every file 0600.
FILE_MODE = 0o666 & ~_process_umask()
TMP_SUFFIX = ".tmp"


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` via a temporary file in the same directory and a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=TMP_SUFFIX)
    try:
        os.fchmod(fd, FILE_MODE)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serializable: {type(o).__name__}")


def dumps(obj: Any) -> str:
    return json.dumps(obj, indent=2, default=_json_default)


def versions() -> dict[str, str]:
    """Versions of Python, dotshell and every distribution providing dotshell plugins."""
    import importlib.metadata as md

    out = {"python": platform.python_version(), "platform": platform.platform()}
    for name in ("dotshell", "numpy", "opencv-python-headless", "open3d", "pyvista", "pluggy"):
        try:
            out[name] = md.version(name)
        except md.PackageNotFoundError:
            pass
    for ep in md.entry_points(group="dotshell"):
        if ep.dist is not None:
            out[f"plugin:{ep.name}"] = f"{ep.dist.name} {ep.dist.version}"
    return out


_MANIFEST_KEYS = {"status": str, "frame_names": list, "views": list}
_VIEW_KEYS = {"index": int, "angle_deg": (int, float), "frames": int, "complete": bool}


def check_manifest(m: Any, path: Path) -> dict[str, Any]:
    """``m`` if it has the keys and types every command relies on; a :class:`RunError` naming
    the first problem otherwise."""
    import math

    def bad(what: str) -> RunError:
        return RunError(f"{path} is damaged: {what}. It is written by dotshell only; restore it "
                        "from a backup, or re-capture the run.")

    if not isinstance(m, dict):
        raise bad(f"it holds a {type(m).__name__}, not an object")
    for key, kind in _MANIFEST_KEYS.items():
        if not isinstance(m.get(key), kind):
            raise bad(f"'{key}' is missing or not a {kind.__name__}")
    for i, v in enumerate(m["views"]):
        if not isinstance(v, dict):
            raise bad(f"views[{i}] is not an object")
        for key, kind in _VIEW_KEYS.items():
            val = v.get(key)
            if not isinstance(val, kind) or (key != "complete" and isinstance(val, bool)):
                raise bad(f"views[{i}].{key} is missing or of the wrong type")
        if not math.isfinite(v["angle_deg"]) or v["index"] != i:
            raise bad(f"views[{i}] has index {v['index']} / angle {v['angle_deg']}")
    if not all(isinstance(n, str) and n for n in m["frame_names"]):
        raise bad("frame_names must be non-empty strings")
    return m


class RunStore:
    """Reads and writes one run directory."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self._events = None

    # ---- creation ---------------------------------------------------------------------------

    @classmethod
    def create(cls, parent: Path, profile_name: str) -> "RunStore":
        """A new, empty run directory ``<parent>/<YYYYmmdd-HHMMSS>_<profile>``."""
        safe = re.sub(r"[^A-Za-z0-9_.-]+", "-", profile_name) or "run"
        stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
        parent = Path(parent)
        if parent.exists() and not parent.is_dir():
            raise RunError(f"--out {parent} is a file, not a directory; give the directory runs "
                           "are written under (it is made if missing).")
        parent.mkdir(parents=True, exist_ok=True)
        for n in range(1000):
            root = parent / (f"{stamp}_{safe}" + (f"_{n}" if n else ""))
            try:
                root.mkdir()
                return cls(root)
            except FileExistsError:
                continue
        raise RunError(f"cannot create a run directory under {parent}: too many runs this second.")

    @classmethod
    def open(cls, root: Path) -> "RunStore":
        """An existing run; raises :class:`RunError` if it is not one."""
        root = Path(root)
        if not (root / "manifest.json").is_file():
            raise RunError(f"{root} is not a dotshell run directory (no manifest.json). Give the "
                           "directory `dotshell scan` printed at the end of a scan.")
        return cls(root)

    # ---- generic files ----------------------------------------------------------------------

    def path(self, *parts: str) -> Path:
        return self.root.joinpath(*parts)

    @property
    def run_root(self) -> Path:
        """The run directory (for a generation's view of the run, its top)."""
        return self.root

    def clean_orphans(self) -> list[Path]:
        """Remove temporary files (``.NAME.*.tmp``) left by a process killed mid-write; call
        only while holding the run's lock. Returns what was removed."""
        gone = []
        for p in [*self.root.rglob(f".*{TMP_SUFFIX}"), *self.root.rglob(f".*{TMP_SUFFIX}.*")]:
            if p.is_file() or p.is_symlink():
                p.unlink()
                gone.append(p)
        return gone

    def write_json(self, name: str, obj: Any) -> Path:
        p = self.path(name)
        atomic_write_text(p, dumps(obj))
        return p

    def read_json(self, name: str) -> Any:
        p = self.path(name)
        try:
            return json.loads(p.read_text())
        except FileNotFoundError:
            raise RunError(f"{p} is missing from the run.") from None
        except json.JSONDecodeError as exc:
            raise RunError(f"{p} is not valid JSON ({exc}).") from None

    def write_profile(self, data: dict[str, Any]) -> Path:
        p = self.path("profile.toml")
        atomic_write_bytes(p, tomli_w.dumps(data).encode())
        return p

    # ---- manifest ---------------------------------------------------------------------------

    def init_manifest(self, profile_name: str, angles_deg: list[float],
                      frame_names: list[str]) -> None:
        self.write_json("manifest.json", {
            "format": RUN_FORMAT,
            "profile": profile_name,
            "created": datetime.now().isoformat(timespec="seconds"),
            "status": "running",
            "versions": versions(),
            "frame_names": frame_names,
            "views": [{"index": i, "angle_deg": a, "frames": 0, "complete": False}
                      for i, a in enumerate(angles_deg)],
        })

    @property
    def manifest(self) -> dict[str, Any]:
        return check_manifest(self.read_json("manifest.json"), self.path("manifest.json"))

    def status(self) -> tuple[str, str]:
        """(status, reason) as it truly is (a ``running`` run whose process is gone is
        ``interrupted``; see :mod:`dotshell.pipeline.lifecycle`)."""
        from dotshell.pipeline.lifecycle import effective_status

        return effective_status(self.root, self.manifest)

    def update_manifest(self, **changes: Any) -> None:
        m = self.manifest
        m.update(changes)
        self.write_json("manifest.json", m)

    def update_report(self, timings_s: dict[str, float] | None = None,
                      **sections: Any) -> dict[str, Any]:
        """Set ``sections`` of ``report.json`` (made if missing) and merge ``timings_s`` (s) into
        its timings, for a stage re-run on an existing run; returns the report."""
        report = self.read_json("report.json") if self.path("report.json").is_file() else {}
        report.update(sections)
        if timings_s:
            report.setdefault("timings_s", {}).update(timings_s)
        self.write_json("report.json", report)
        return report

    def mark_view(self, view: int, frames: int, complete: bool) -> None:
        m = self.manifest
        m["views"][view].update(frames=frames, complete=complete)
        self.write_json("manifest.json", m)

    # ---- frames -----------------------------------------------------------------------------

    def frame_path(self, view: int, index: int, name: str) -> Path:
        return self.path("frames", f"view_{view:03d}", f"{index:03d}_{name}.png")

    def write_frame(self, view: int, index: int, name: str, image: np.ndarray) -> Path:
        """Write one captured frame losslessly (PNG; uint8 or uint16)."""
        return self.write_image(self.frame_path(view, index, name), image,
                                f"frame {name} of view {view}")

    def write_image(self, path: Path, image: np.ndarray, label: str) -> Path:
        """Write a captured image losslessly (PNG; 2-D uint8 or uint16) at ``path`` inside the
        run; ``label`` names it in errors."""
        if image.dtype not in (np.uint8, np.uint16) or image.ndim != 2:
            raise RunError(f"{label} is {image.dtype} {image.shape}; cameras must return 2-D "
                           "uint8 or uint16 images.")
        ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if not ok:
            raise RunError(f"could not encode {label} as PNG.")
        atomic_write_bytes(path, buf.tobytes())
        return path

    def read_image(self, path: Path, why: str) -> np.ndarray:
        """A stored image as written; ``why`` says what cannot be done without it."""
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise RunError(f"{path} is missing or unreadable; {why}.")
        return img

    def trans_path(self, name: str, view: int | None = None) -> Path:
        """Path of a trans-illumination image: ``transillumination/view_VVV/NAME.png`` for a
        view's frames, ``transillumination/NAME.png`` for the flat field."""
        if view is None:
            return self.path("transillumination", f"{name}.png")
        return self.path("transillumination", f"view_{view:03d}", f"{name}.png")

    def read_frames(self, view: int) -> list[np.ndarray]:
        """All frames of a view in capture order, as written."""
        names = self.manifest["frame_names"]
        return [self.read_image(self.frame_path(view, i, name),
                                f"view {view} cannot be reconstructed")
                for i, name in enumerate(names)]

    # ---- events -----------------------------------------------------------------------------

    def append_event(self, record: dict[str, Any]) -> None:
        """Append one JSON line to ``events.jsonl`` and flush it."""
        if self._events is None:
            self._events = open(self.path("events.jsonl"), "a", encoding="utf-8")
        self._events.write(json.dumps(record, default=_json_default) + "\n")
        self._events.flush()

    def close(self) -> None:
        if self._events is not None:
            self._events.close()
            self._events = None

    def events(self) -> list[dict[str, Any]]:
        p = self.path("events.jsonl")
        if not p.is_file():
            return []
        return [json.loads(line) for line in p.read_text().splitlines() if line.strip()]


