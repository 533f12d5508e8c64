"""RunStore: one scan's run directory. Every file is written to a temporary name and renamed
(atomic on POSIX), frames are written losslessly (:mod:`dotshell.run.frames`, 8 or 16 bit) as they
arrive, and ``events.jsonl`` is appended and flushed per event — a crash loses nothing already
written.

Every name in the run directory is :class:`~dotshell.run.layout.RunLayout`'s (see
``docs/run-directory.md``).
"""

from __future__ import annotations

import errno
import json
import math
import os
import platform
import re
import secrets
import tomllib
from datetime import datetime
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np
import tomli_w

from dotshell.errors import RunError
from dotshell.run.framecheck import FrameSpec
from dotshell.run.frames import CURRENT_FORMAT, FrameStore, check_image, open_frames
from dotshell.run.lost import check_lost_entry
from dotshell.run.layout import RunLayout

RUN_FORMAT = "dotshell-run/1"


TMP_SUFFIX = ".tmp"
#: A run's reserve: space held back so the manifest can still be written when the disk fills
#: up (deleted by the first manifest write that meets a full disk, and at the end of each job).
RESERVE = RunLayout.RESERVE
RESERVE_BYTES = 256 * 1024
FULL = (errno.ENOSPC, errno.EDQUOT)


def temp_beside(path: Path) -> tuple[int, Path]:
    """A new, empty temporary file ``.NAME.XXXXXXXX.tmp`` beside ``path``, open for writing.
    Created with mode 0666 so the process's umask decides its permissions, as for any file the
    user makes (``mkstemp`` would make every file 0600: a lab group could not read runs)."""
    path = Path(path)
    for _ in range(100):
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}{TMP_SUFFIX}")
        try:
            return os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o666), tmp
        except FileExistsError:
            continue
    raise FileExistsError(errno.EEXIST, "no free temporary name", str(path))


def atomic_write_bytes(path: Path, data: bytes | memoryview) -> None:
    """Write ``data`` (bytes, or a memoryview of a buffer such as a numpy array's, written
    without a copy) to ``path`` via a temporary file in the same directory and a rename. A
    failure names ``path`` (not the temporary file) and leaves ``path`` as it was."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = temp_beside(path)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(exc, OSError) and exc.errno is not None:
            raise OSError(exc.errno, exc.strerror, str(path)) from None
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
    from dotshell.plugins import distribution_of

    for ep in md.entry_points(group="dotshell"):
        if ep.dist is not None:
            out[f"plugin:{ep.name}"] = distribution_of(ep)[1]
    return out


_MANIFEST_KEYS = {"status": str, "frame_names": list, "views": list}
_VIEW_KEYS: dict[str, type | tuple[type, ...]] = {"index": int, "angle_deg": (int, float), "frames": int, "complete": bool}


def _number(v: Any, integer: bool = False) -> bool:
    """A finite number (an int when ``integer``), not a bool."""
    kinds = int if integer else (int, float)
    return isinstance(v, kinds) and not isinstance(v, bool) and math.isfinite(v)


def check_manifest(m: Any, path: Path) -> dict[str, Any]:
    """``m`` if it has the keys, types and counts every command relies on; a
    :class:`RunError` naming the first problem otherwise."""

    def bad(what: str) -> RunError:
        return RunError(f"{path} is damaged: {what}. It is written by dotshell only; restore it "
                        "from a backup, or re-capture the run.")

    if not isinstance(m, dict):
        raise bad(f"it holds a {type(m).__name__}, not an object")
    for key, kind in _MANIFEST_KEYS.items():
        if not isinstance(m.get(key), kind):
            raise bad(f"'{key}' is missing or not a {kind.__name__}")
    if not all(isinstance(n, str) and n for n in m["frame_names"]):
        raise bad("frame_names must be non-empty strings")
    n_names = len(m["frame_names"])
    for i, v in enumerate(m["views"]):
        if not isinstance(v, dict):
            raise bad(f"views[{i}] is not an object")
        for key, kinds in _VIEW_KEYS.items():
            val = v.get(key)
            if not isinstance(val, kinds) or (key != "complete" and isinstance(val, bool)):
                raise bad(f"views[{i}].{key} is missing or of the wrong type")
        if not math.isfinite(v["angle_deg"]) or v["index"] != i:
            raise bad(f"views[{i}] has index {v['index']} / angle {v['angle_deg']}")
        lost_problem = check_lost_entry(v.get("lost"))
        if lost_problem is not None:
            raise bad(f"views[{i}].{lost_problem}")
        if "angle_read_deg" in v and not _number(v["angle_read_deg"]):
            raise bad(f"views[{i}].angle_read_deg = {v['angle_read_deg']!r} is not a finite "
                      "number of degrees")
        if not 0 <= v["frames"] <= n_names or (v["complete"] and v["frames"] != n_names):
            raise bad(f"views[{i}] counts {v['frames']} frames "
                      f"({'complete' if v['complete'] else 'incomplete'}) of a sequence of "
                      f"{n_names}")
    if "shots" in m:
        _check_shots(m["shots"], m["frame_names"], bad)
    _check_camera_entry(m.get("camera"), bad)
    _check_trans_entry(m.get("transillumination"), bad)
    return m


def _check_shots(shots: Any, names: list[str], bad) -> None:
    """``shots``: per frame of the sequence, its ``name``, ``pattern`` index and analyzer angle
    (degrees or null); every pattern shot once, or twice (PDI)."""
    if not isinstance(shots, list) or len(shots) != len(names):
        raise bad(f"'shots' must list the {len(names)} frames of frame_names")
    for i, (shot, name) in enumerate(zip(shots, names)):
        if not (isinstance(shot, dict) and shot.get("name") == name
                and _number(shot.get("pattern"), True) and 0 <= shot["pattern"] < len(names)
                and "analyzer_deg" in shot
                and (shot["analyzer_deg"] is None or _number(shot["analyzer_deg"]))):
            raise bad(f"shots[{i}] is not {{name: {name!r}, pattern: N, analyzer_deg: degrees "
                      "or null}")
    counts = [0] * (max(s["pattern"] for s in shots) + 1) if shots else []
    for s in shots:
        counts[s["pattern"]] += 1
    if any(c not in (1, 2) for c in counts):
        raise bad("'shots' must take every pattern once (or twice, with PDI)")


def _check_camera_entry(cam: Any, bad) -> None:
    """``camera``: what the run's frames are (``width``, ``height`` px, ``bit_depth``)."""
    if cam is None:
        return
    if not isinstance(cam, dict):
        raise bad("'camera' is not an object")
    for key in ("width", "height"):
        if not (_number(cam.get(key), True) and cam[key] > 0):
            raise bad(f"camera.{key} = {cam.get(key)!r} is not a positive integer")
    if not (_number(cam.get("bit_depth"), True) and 1 <= cam["bit_depth"] <= 16):
        raise bad(f"camera.bit_depth = {cam.get('bit_depth')!r} is not 1..16")


def _check_trans_entry(t: Any, bad) -> None:
    if t is None:
        return
    if not isinstance(t, dict):
        raise bad("'transillumination' is not an object")
    if not (_number(t.get("exposure_ms")) and t["exposure_ms"] > 0):
        raise bad(f"transillumination.exposure_ms = {t.get('exposure_ms')!r} is not a positive "
                  "number of ms")
    if not (_number(t.get("camera_bit_depth"), True) and 1 <= t["camera_bit_depth"] <= 16):
        raise bad(f"transillumination.camera_bit_depth = {t.get('camera_bit_depth')!r} is not "
                  "1..16")
    targets, views = t.get("targets_mm"), t.get("views")
    if not isinstance(targets, list) or not targets or not all(
            x is None or (isinstance(x, list) and len(x) == 2 and all(map(_number, x)))
            for x in targets):
        raise bad("transillumination.targets_mm must be a list of [lateral, height] mm or null")
    if not isinstance(views, dict) or not all(
            isinstance(k, str) and k.isdigit() and isinstance(v, list)
            and all(isinstance(n, str) and n for n in v) for k, v in views.items()):
        raise bad("transillumination.views must map view numbers to lists of frame names")
    if t.get("flat_field") is not None and not isinstance(t["flat_field"], str):
        raise bad("transillumination.flat_field must be a path in the run or null")


class RunStore:
    """Reads and writes one run directory."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self._events: Any = None  # the open log; False once it cannot be written
        self._reserve_used = False

    # ---- creation ---------------------------------------------------------------------------

    @classmethod
    def create(cls, parent: Path, profile_name: str) -> RunStore:
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
    def open(cls, root: Path) -> RunStore:
        """An existing run; raises :class:`RunError` if it is not one."""
        root = Path(root)
        if not (root / RunLayout.MANIFEST).is_file():
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
        """Write a JSON file of the run atomically. On a full disk the run's reserve is given
        up once so the manifest can still say what is true (frames counted, the failure)."""
        p = self.path(name)
        text = dumps(obj)
        try:
            atomic_write_text(p, text)
        except OSError as exc:
            if exc.errno not in FULL or not self.release_reserve():
                raise
            atomic_write_text(p, text)
        return p

    def reserve_space(self) -> OSError | None:
        """Hold :data:`RESERVE_BYTES` back in the run (see :data:`RESERVE`); returns the error
        of a disk already too full for it (or a size limit), met later by the writes
        themselves unless the caller stops first."""
        p = self.path(RESERVE)
        if p.is_file():
            return None
        try:
            atomic_write_bytes(p, bytes(RESERVE_BYTES))
        except OSError as exc:
            if exc.errno not in (*FULL, errno.EFBIG):  # no room (or a size limit): go without
                raise
            return exc
        return None

    def release_reserve(self) -> bool:
        """Give the reserve back to the file system; whether there was one. From then on this
        store writes no more images (:meth:`write_image`): the space is the manifest's."""
        try:
            os.unlink(self.path(RESERVE))
        except FileNotFoundError:
            return False
        self._reserve_used = True
        return True

    def read_json(self, name: str) -> Any:
        return self._parse(name, json.loads, json.JSONDecodeError, "is missing from the run.",
                           "is not valid JSON ({exc}); it is written by dotshell only: restore "
                           "it from a backup.")

    def read_profile(self) -> dict[str, Any]:
        """The run's ``profile.toml`` as recorded (validated and defaults filled in when it was
        written), parsed; RunError naming the file when it is missing or damaged."""
        return self._parse(RunLayout.PROFILE, tomllib.loads, tomllib.TOMLDecodeError,
                           "is missing; this run cannot be re-processed.",
                           "is damaged ({exc}); it is written by dotshell only — restore it "
                           "from a backup or copy the profile the run was made with.")

    def _parse(self, name: str, parse: Callable[[str], Any], error: type[Exception],
               missing: str, damaged: str) -> Any:
        p = self.path(name)
        try:
            return parse(p.read_text())
        except FileNotFoundError:
            raise RunError(f"{p} {missing}") from None
        except (error, UnicodeDecodeError, RecursionError) as exc:
            raise RunError(f"{p} {damaged.format(exc=exc)}") from None

    def write_profile(self, data: dict[str, Any]) -> Path:
        p = self.path(RunLayout.PROFILE)
        atomic_write_bytes(p, tomli_w.dumps(data).encode())
        return p

    # ---- manifest ---------------------------------------------------------------------------

    def init_manifest(self, profile_name: str, angles_deg: list[float],
                      frame_names: list[str]) -> None:
        self.write_json(RunLayout.MANIFEST, {
            "format": RUN_FORMAT,
            "profile": profile_name,
            "created": datetime.now().isoformat(timespec="seconds"),
            "status": "running",
            "versions": versions(),
            "frame_format": CURRENT_FORMAT,
            "frame_names": frame_names,
            "views": [{"index": i, "angle_deg": a, "frames": 0, "complete": False}
                      for i, a in enumerate(angles_deg)],
        })

    @property
    def manifest(self) -> dict[str, Any]:
        return check_manifest(self.read_json(RunLayout.MANIFEST), self.path(RunLayout.MANIFEST))

    def status(self) -> tuple[str, str]:
        """(status, reason) as it truly is (a ``running`` run whose process is gone is
        ``interrupted``; see :mod:`dotshell.run.lifecycle`)."""
        from dotshell.run.lifecycle import effective_status

        return effective_status(self.root, self.manifest)

    def update_manifest(self, **changes: Any) -> None:
        m = self.manifest
        m.update(changes)
        self.write_json(RunLayout.MANIFEST, m)

    def update_report(self, timings_s: dict[str, float] | None = None,
                      **sections: Any) -> dict[str, Any]:
        """Set ``sections`` of ``report.json`` (made if missing) and merge ``timings_s`` (s) into
        its timings, for a stage re-run on an existing run; returns the report."""
        report = self.read_json(RunLayout.REPORT) if self.path(RunLayout.REPORT).is_file() else {}
        report.update(sections)
        if timings_s:
            report.setdefault("timings_s", {}).update(timings_s)
        self.write_json(RunLayout.REPORT, report)
        return report

    def mark_view(self, view: int, frames: int, complete: bool) -> None:
        m = self.manifest
        m["views"][view].update(frames=frames, complete=complete)
        if complete:  # captured whole again (`resume --view N`): no longer lost
            m["views"][view].pop("lost", None)
        self.write_json(RunLayout.MANIFEST, m)

    # ---- frames -----------------------------------------------------------------------------

    def frames(self, view: int) -> FrameStore:
        """The stored frames of a view (to read, or to append to as they arrive)."""
        return open_frames(self.run_root, view, self.manifest)

    def check_room(self, path: Path) -> None:
        """Raise ``OSError(ENOSPC)`` for ``path`` once the run's reserve was used: the space
        left is the manifest's, no more images are written."""
        if self._reserve_used:
            raise OSError(errno.ENOSPC, "No space left on device (the run's reserve was used "
                          "to record the run's state)", str(path))

    def write_image(self, path: Path, image: np.ndarray, label: str) -> Path:
        """Write a captured image losslessly (PNG; 2-D uint8 or uint16) at ``path`` inside the
        run; ``label`` names it in errors."""
        check_image(image, label)
        self.check_room(path)
        ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if not ok:
            raise RunError(f"could not encode {label} as PNG.")
        atomic_write_bytes(path, buf.tobytes())
        return path

    def read_image(self, path: Path, why: str) -> np.ndarray:
        """A stored image as written; ``why`` says what cannot be done without it."""
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise RunError(f"{path} is missing or unreadable; {why}. Restore it from a backup "
                           "of the run.")
        return img

    def trans_path(self, name: str, view: int | None = None) -> Path:
        """Path of a trans-illumination image: ``transillumination/view_VVV/NAME.png`` for a
        view's frames, ``transillumination/NAME.png`` for the flat field."""
        return self.path(RunLayout.trans_frame(name, view))

    def read_frames(self, view: int, spec: FrameSpec | None = None, fix: str = "",
                    out: np.ndarray | None = None) -> np.ndarray:
        """All frames of a view in capture order, as written: (frames, height, width); with a
        ``spec``, each checked against it; ``out``: an array to reuse (see
        :meth:`FrameStore.read_all`)."""
        return self.frames(view).read_all(spec, fix, out)

    # ---- events -----------------------------------------------------------------------------

    def append_event(self, record: dict[str, Any]) -> None:
        """Append one JSON line to ``events.jsonl`` and flush it. A line cut short by a writer
        that was killed is ended first, so it never swallows the next event. Once the log
        cannot be written (a full disk), events are dropped after one error saying so."""
        if self._events is False:
            return
        try:
            if self._events is None:
                self._events = open(self.path(RunLayout.EVENTS), "a+b")  # noqa: SIM115 (held open)
                if self._events.tell() > 0:
                    self._events.seek(-1, os.SEEK_END)
                    if self._events.read(1) != b"\n":
                        self._events.write(b"\n")
            line = json.dumps(record, default=_json_default) + "\n"
            self._events.write(line.encode("utf-8"))
            self._events.flush()
        except OSError as exc:
            self.close()
            self._events = False
            raise RunError(f"{self.path(RunLayout.EVENTS)} cannot be appended ({exc.strerror}); "
                           "the run's event log misses the events from here on (the manifest "
                           "and frames are still written).") from None

    def close(self) -> None:
        if self._events:
            try:
                self._events.close()
            except OSError:
                pass
        self._events = None

    def events(self) -> list[dict[str, Any]]:
        """The event log's records; a line that is not a JSON object (cut short by a killed
        writer, or damaged) is skipped."""
        p = self.path(RunLayout.EVENTS)
        if not p.is_file():
            return []
        out = []
        for line in p.read_bytes().splitlines():
            try:
                record = json.loads(line)
            except ValueError:  # UnicodeDecodeError included
                continue
            if isinstance(record, dict):
                out.append(record)
        return out


