"""Generations: the products of each processing job are written into a directory of their own
and published together, so a re-run never overwrites what it is based on and a reader never
sees products of two jobs mixed.

Layout (``docs/run-directory.md``)::

    <run>/gen/001/      views/ cloud.ply report.json previews/ surface.ply ... products.json
    <run>/gen/002/      the next job's products (files it did not change are hard links)
    <run>/current  ->   gen/002   a symbolic link, replaced atomically on publication
    <run>/cloud.ply ->  current/cloud.ply   (and one such link per product name, for people
                                             and tools that look at the run's top level)

``products.json`` (written last, just before publication) lists the files of each product
(``views``, ``cloud``, ``mesh``, ...) so the next generation can carry the unchanged ones over.
Capture items — frames, trans-illumination frames, the manifest, the profile, the capture-time
calibration, the event log — live at the top of the run and belong to no generation.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path
from typing import Any, Iterable

from dotshell.errors import RunError
from dotshell.run.layout import RunLayout
from dotshell.run.store import RunStore, atomic_write_text, dumps

L = RunLayout
GEN_DIR = L.GEN
CURRENT = L.CURRENT
PRODUCTS_FILE = L.PRODUCTS
#: Top-level names that are the capture (or bookkeeping), never products.
CAPTURE_ITEMS = frozenset({L.MANIFEST, L.PROFILE, L.CALIBRATION, L.EVENTS, L.LOCK, L.FRAMES,
                           L.TRANSILLUMINATION, GEN_DIR, CURRENT, L.SERVER_LOG, L.SNAPSHOTS,
                           L.LIVE, L.TRUTH, L.TRUTH_DIR})
#: Where products of runs made before generations existed (format dotshell-run/1) are found.
LEGACY_PRODUCTS = {L.VIEWS: "views", L.CLOUD: "cloud", L.REPORT: "report", L.SURFACE: "mesh",
                   L.VOLUME: "mesh", L.OPTODES: "mesh", L.MESHES: "mesh",
                   L.NORMALIZE: "normalize", L.FORWARD: "forward"}


def _number(name: str) -> int | None:
    return int(name) if re.fullmatch(r"\d{3,}", name) else None


def generation_numbers(root: Path) -> list[int]:
    d = Path(root) / GEN_DIR
    if not d.is_dir():
        return []
    return sorted(n for p in d.iterdir() if (n := _number(p.name)) is not None)


def current_number(root: Path) -> int | None:
    """The published generation, or None."""
    link = Path(root) / CURRENT
    try:
        target = os.readlink(link)
    except OSError:
        return None
    return _number(Path(target).name)


def _files_under(base: Path, rel: str) -> list[str]:
    p = base / rel
    if p.is_dir() and not p.is_symlink():
        return sorted(str(f.relative_to(base)) for f in p.rglob("*") if f.is_file())
    return [rel] if p.is_file() else []


def _link_or_copy(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(src, dst)
    except OSError:  # a file system without hard links
        shutil.copy2(src, dst)


class Generation:
    """One generation being written (``gen/NNN``) by one job; see the module docstring."""

    def __init__(self, run: RunStore, number: int, base: int | None) -> None:
        self.run = run
        self.number = number
        self.base = base
        self.dir = run.path(L.generation_dir(number))
        self.files: dict[str, list[str]] = {}
        self.report: dict[str, Any] = {}
        #: the published generation, when its directory is missing (deleted)
        self.missing_base: int | None = None

    @classmethod
    def start(cls, run: RunStore) -> Generation:
        """A new, empty generation after the highest existing one, based on the published one."""
        adopt_legacy_products(run)
        base = current_number(run.root)
        missing = None
        if base is not None and not run.path(L.generation_dir(base)).is_dir():
            missing, base = base, None  # deleted: everything is made again from the frames
        number = max(generation_numbers(run.root), default=0) + 1
        gen = cls(run, number, base)
        gen.missing_base = missing
        gen.dir.mkdir(parents=True)
        return gen

    # ---- the base generation ---------------------------------------------------------------

    def base_dir(self) -> Path | None:
        return None if self.base is None else self.run.path(L.generation_dir(self.base))

    def base_products(self) -> dict[str, list[str]]:
        d = self.base_dir()
        if d is None or not (d / PRODUCTS_FILE).is_file():
            return {}
        try:
            data = json.loads((d / PRODUCTS_FILE).read_text())
            return {str(k): [str(f) for f in v] for k, v in data["files"].items()}
        except (OSError, ValueError, KeyError, TypeError, AttributeError, RecursionError) as exc:
            raise RunError(f"{d / PRODUCTS_FILE} is damaged ({exc}); re-process the run from "
                           "its frames with `dotshell reconstruct RUN`.") from None

    def base_report(self) -> dict[str, Any]:
        d = self.base_dir()
        p = None if d is None else d / L.REPORT
        if p is None or not p.is_file():
            return {}
        try:
            report = json.loads(p.read_text())
        except (ValueError, RecursionError) as exc:
            raise RunError(f"{p} is not valid JSON ({exc}); re-process the run with "
                           "`dotshell reconstruct RUN`.") from None
        return report if isinstance(report, dict) else {}

    def carry(self, products: Iterable[str]) -> None:
        """Hard-link the base generation's files of ``products`` into this one."""
        base, have = self.base_dir(), self.base_products()
        for product in products:
            if product not in have or base is None:
                continue
            for rel in have[product]:
                if (base / rel).is_file():
                    _link_or_copy(base / rel, self.dir / rel)
            self.files[product] = list(have[product])

    # ---- what steps write ------------------------------------------------------------------

    def listing(self) -> set[str]:
        return {str(p.relative_to(self.dir)) for p in self.dir.rglob("*") if p.is_file()}

    def record(self, product: str, before: set[str]) -> None:
        """Assign the files written since ``before`` (a :meth:`listing`) to ``product``."""
        new = sorted(self.listing() - before - {PRODUCTS_FILE, L.REPORT})
        if new:
            self.files[product] = sorted(set(self.files.get(product, [])) | set(new))

    def drop(self, product: str) -> None:
        """Remove a carried product (it would be stale)."""
        for rel in self.files.pop(product, []):
            p = self.dir / rel
            if p.is_file():
                p.unlink()

    # ---- publication -----------------------------------------------------------------------

    def publish(self) -> None:
        """Write ``report.json`` and ``products.json`` (last), then make this generation the
        run's ``current`` in one atomic rename, and link new product names at the top."""
        atomic_write_text(self.dir / L.REPORT, dumps(self.report))
        atomic_write_text(self.dir / PRODUCTS_FILE,
                          dumps({"generation": self.number, "based_on": self.base,
                                 "files": self.files}))
        point_current(self.run.root, self.number)
        link_top_level(self.run.root, self.dir)


def published(root: Path, number: int) -> bool:
    """Whether generation ``number`` was ever published (it has its ``products.json``)."""
    return (Path(root) / L.generation_dir(number) / PRODUCTS_FILE).is_file()


def remove_unpublished(root: Path, only: int | None = None) -> list[Path]:
    """Delete generations a failed or killed job left half-written (never published); call
    only while holding the run's lock. Returns what was removed."""
    cur = current_number(root)
    gone = []
    for n in generation_numbers(root):
        if (only is None or n == only) and n != cur and not published(root, n):
            d = Path(root) / L.generation_dir(n)
            shutil.rmtree(d)
            gone.append(d)
    return gone


def point_current(root: Path, number: int) -> None:
    tmp = Path(root) / f".{CURRENT}.{os.getpid()}.tmp"
    if tmp.is_symlink() or tmp.exists():
        tmp.unlink()
    os.symlink(L.generation_dir(number), tmp)
    os.replace(tmp, Path(root) / CURRENT)


def link_top_level(root: Path, gen_dir: Path) -> None:
    """``<run>/NAME -> current/NAME`` for each top-level entry of a generation (links through
    ``current`` stay right when it moves on; a name the current generation lacks dangles)."""
    for entry in gen_dir.iterdir():
        name = entry.name
        if name in CAPTURE_ITEMS or name.startswith(".") or name == PRODUCTS_FILE:
            continue
        top = Path(root) / name
        if name == L.PREVIEWS:
            _move_live_frame(Path(root), top)
        if not os.path.lexists(top):
            os.symlink(f"{CURRENT}/{name}", top)


def _move_live_frame(root: Path, top: Path) -> None:
    """Runs scanned from a session before ``live/`` existed hold the live frame in a real
    ``previews/`` folder, which kept the ``previews`` link from being made: a folder holding
    nothing else is moved to ``live/`` so the link is made now."""
    if top.is_symlink() or not top.is_dir():
        return
    entries = list(top.iterdir())
    if any(p.name != Path(L.LATEST_FRAME).name for p in entries):
        return  # someone's own files: left where they are
    (root / L.LIVE).mkdir(exist_ok=True)
    for p in entries:
        os.replace(p, root / L.LIVE / p.name)
    top.rmdir()


def adopt_legacy_products(run: RunStore) -> None:
    """Move the products of a run written before generations (top-level ``cloud.ply``,
    ``views/``, ``report.json`` ...) into ``gen/000`` and publish it, so they are kept, not
    overwritten. Idempotent (an interrupted adoption finishes the next time)."""
    root = run.root
    cur = root / CURRENT
    if cur.is_dir() and not cur.is_symlink():
        raise RunError(f"{cur} is a directory, not a symbolic link: the run was copied without "
                       "keeping its links (copy runs with `cp -a` or `rsync -a`). Copy it again "
                       "from the original, or re-process the frames in a new run.")
    if cur.is_symlink():  # a run with generations (or adopted already): other files are not
        return            # products (a user's notes stay where they are)
    legacy = [p for p in root.iterdir()
              if p.name not in CAPTURE_ITEMS and not p.name.startswith(".")
              and not p.is_symlink()]
    if not legacy:
        return
    gen0 = root / L.generation_dir(0)
    gen0.mkdir(parents=True, exist_ok=True)
    for p in legacy:
        os.replace(p, gen0 / p.name)
    if (root / L.CALIBRATION).is_file() and not (gen0 / L.CALIBRATION).exists():
        _link_or_copy(root / L.CALIBRATION, gen0 / L.CALIBRATION)
    files: dict[str, list[str]] = {}
    for p in sorted(gen0.iterdir()):
        if p.name == PRODUCTS_FILE:
            continue
        product = LEGACY_PRODUCTS.get(p.name, p.name if p.name in (L.PREVIEWS, L.CALIBRATION)
                                      else "exports").replace(L.CALIBRATION, "calibration")
        if product == "report":
            continue
        files.setdefault(product, []).extend(_files_under(gen0, p.name))
    atomic_write_text(gen0 / PRODUCTS_FILE, dumps({"generation": 0, "based_on": None,
                                                   "files": files, "adopted": True}))
    if current_number(root) is None:
        point_current(root, 0)
    link_top_level(root, gen0)


class ProductStore(RunStore):
    """The run as a step sees it: products are read and written in one generation's directory
    (``root``), the capture (frames, manifest, event log) at the run's top (``run``)."""

    def __init__(self, run: RunStore, generation_dir: Path) -> None:
        super().__init__(generation_dir)
        self.run = run

    @property
    def run_root(self) -> Path:
        return self.run.root

    def path(self, *parts: str) -> Path:
        names = Path(*parts).parts if parts else ()
        first = names[0] if names else ""
        if first in CAPTURE_ITEMS and first != L.CALIBRATION:
            return self.run.path(*parts)
        return super().path(*parts)

    def append_event(self, record: dict[str, Any]) -> None:
        self.run.append_event(record)

    def close(self) -> None:
        pass
