"""Harness of the fault matrix (tests/test_faults.py): a case is a command line made by a setup
function, run through the real ``dotshell.cli.app.main``; the harness checks the exit code, the
one-paragraph message, and that nothing that existed before was changed or lost.

Faults of the file system are made two ways:

* :class:`FullDisk` (in process, always available): writes of dotshell's atomic writer
  (``os.fdopen`` on a temporary file) under a directory draw on a byte budget; a write that does
  not fit raises the kernel's ``OSError(ENOSPC)`` (or ``EDQUOT``) exactly as ``write(2)`` does
  on a full disk, and its bytes are given back as the writer deletes its temporary file. Chosen
  because it fails at a chosen byte without root, loops or mounts, and it is the same
  exception the code sees from a real disk.
* :func:`in_tmpfs` (a subprocess in a private mount namespace, ``unshare -rm``): a real tmpfs of
  a few kilobytes or inodes, or read-only — the kernel itself refuses, and every path (the
  event log, directories, links) meets it. Skipped where user namespaces are not allowed.
"""

from __future__ import annotations

import builtins
import errno
import hashlib
import json
import os
import shlex
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import pytest

from conftest import ROOT, make_dist, small_profile_dict, write_profile

#: Files a failing command may change: the lock (its holder), the event log (appended), the
#: manifest's job history (checked separately: everything else in it must stay).
BOOKKEEPING = {".lock", "events.jsonl", "manifest.json"}


def digest_tree(root: Path) -> dict[str, bytes]:
    """Content of every regular file under ``root`` (symbolic links not followed)."""
    if not root.exists():
        return {}
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and not p.is_symlink() and "__pycache__" not in p.parts}


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()[:12]


def _without_jobs(data: bytes) -> Any:
    try:
        m = json.loads(data)
    except ValueError:
        return data
    if isinstance(m, dict):
        for k in ("jobs", "job"):
            m.pop(k, None)
    return m


def unchanged(before: dict[str, bytes], after: dict[str, bytes], state_may_change: bool) -> list[str]:
    """Names of files of ``before`` changed or lost in ``after``. Bookkeeping files may change
    only as bookkeeping: the lock freely, the event log by appending, the manifest in its job
    history (and in its status when ``state_may_change``)."""
    bad = []
    for name, data in before.items():
        base = Path(name).name
        new = after.get(name)
        if new is None and base.startswith(".") and base.endswith(".tmp"):
            continue  # an orphan of an interrupted write, not data
        if new is None:
            bad.append(f"{name} lost")
        elif new == data or base == ".lock":
            continue
        elif base == "events.jsonl" and new.startswith(data):
            continue
        elif base == "manifest.json":
            old_m, new_m = _without_jobs(data), _without_jobs(new)
            if state_may_change and isinstance(old_m, dict) and isinstance(new_m, dict):
                for m in (old_m, new_m):
                    m.pop("status", None)
                    m.pop("reason", None)
            if old_m != new_m:
                bad.append(f"{name} changed beyond its job history")
        else:
            bad.append(f"{name} changed ({sha(data)} -> {sha(new)})")
    return bad


# ---- the environment a case sets up ------------------------------------------------------------

@dataclass
class Env:
    """What a case's setup may use: a fresh ``tmp``, ``monkeypatch``, copies of the module's
    shared runs, plugins installed for this case only, and clean-up callbacks."""

    tmp: Path
    monkeypatch: pytest.MonkeyPatch
    shared: Callable[[str], Path]
    cleanups: list[Callable[[], None]] = field(default_factory=list)
    n_runs: int = 0
    plugins: list[str] = field(default_factory=list)  # modules installed for this case

    def run(self, kind: str = "base") -> Path:
        """A private copy (``cp -a``: links kept) of a shared run."""
        self.n_runs += 1
        dst = self.tmp / f"run{self.n_runs}"
        subprocess.run(["cp", "-a", str(self.shared(kind)), str(dst)], check=True)
        return dst

    def profile(self, name: str = "p.toml", raw: dict | None = None, **changes: Any) -> Path:
        """The tiny profile with ``a__b__c=value`` changes (``None`` deletes the key)."""
        return write_profile(self.tmp / name, tiny_profile_dict(raw, **changes))

    def plugin(self, source: str, entry_point: str = "faulty") -> None:
        """Install a one-module plugin distribution for this case (its module named after its
        source, so cases with different sources never share a cached module)."""
        module = f"dotshell_fault_{sha(source.encode())}"
        dist = f"dotshell-fault-{entry_point}"
        site = self.tmp / f"site-{module}"
        if not site.exists():
            make_dist(site, dist, module, source, entry_point)
        self.monkeypatch.syspath_prepend(str(site))
        self.plugins.append(module)

    def manifest_plugin(self, manifest: str, modules: dict[str, str],
                        entry_point: str = "faulty") -> str:
        """Install a plugin package with a ``dotshell.toml`` manifest and ``modules`` (its
        name after its content, as :meth:`plugin`; ``PKG`` in the manifest is replaced by it);
        the package's name."""
        package = f"dotshell_fault_{sha((manifest + repr(sorted(modules.items()))).encode())}"
        site = self.tmp / f"site-{package}"
        if not site.exists():
            make_dist(site, f"dotshell-fault-{entry_point}", package, "", entry_point)
            (site / f"{package}.py").unlink()
            (site / package).mkdir()
            (site / package / "__init__.py").write_text("")
            (site / package / "dotshell.toml").write_text(manifest.replace("PKG", package))
            for name, source in modules.items():
                (site / package / f"{name}.py").write_text(source)
        self.monkeypatch.syspath_prepend(str(site))
        self.plugins.append(package)
        return package

    def file(self, name: str, content: str | bytes | Any) -> Path:
        """A file in ``tmp``: bytes or text as given, anything else as JSON."""
        p = self.tmp / name
        p.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(content, bytes):
            p.write_bytes(content)
        elif isinstance(content, str):
            p.write_text(content)
        else:
            p.write_text(json.dumps(content))
        return p


def tiny_profile_dict(raw: dict | None = None, **changes: Any) -> dict:
    """A 2-view profile at 0.1 scale (128x102 camera), one ray per pixel, previews off."""
    if raw is None:
        raw = small_profile_dict(factor=0.1, views=2)
        raw["camera"]["settings"]["supersample"] = 1
        raw["outputs"] = {"previews": False}
        # the cases' camera wrappers act in capture(); faults of hardware-sequenced runs are
        # in tests/test_sequenced.py
        raw["scan"]["acquisition"] = "show-capture"
    for dotted, value in changes.items():
        *path, key = dotted.split("__")
        d = raw
        for p in path:
            d = d.setdefault(p, {})
        if value is None:
            d.pop(key, None)
        else:
            d[key] = value
    return raw


def edit_json(path: Path, change: Callable[[Any], Any]) -> None:
    """Rewrite a JSON file in place (through its link, if it is one) with ``change(data)``."""
    path = Path(path).resolve()
    data = change(json.loads(path.read_text()))
    text = data if isinstance(data, str) else json.dumps(data)
    path.unlink()  # a fresh inode: hard-linked copies in other generations stay as they were
    path.write_text(text)


def replace_file(path: Path, content: bytes | str) -> None:
    """Replace a run file (a new inode, so hard links elsewhere keep the original)."""
    path = Path(path).resolve()
    path.unlink()
    if isinstance(content, str):
        content = content.encode()
    path.write_bytes(content)


def frames_on_disk(run: Path, view: int) -> int:
    """Frames of a view readable on disk, counted without dotshell's reader: complete pages of
    the view's TIFF stack (tifffile), or PNG files in runs made before stacks."""
    import tifffile

    stack = run / "frames" / f"view_{view:03d}.tif"
    if stack.is_file():  # a stack cut short mid-page: its whole pages
        n = 0
        size = stack.stat().st_size
        try:
            with tifffile.TiffFile(stack) as tif:
                for page in tif.pages:  # whole: its data inside the file
                    if page.dataoffsets[-1] + page.databytecounts[-1] > size:
                        break
                    n += 1
        except Exception:
            pass
        return n
    d = run / "frames" / f"view_{view:03d}"
    return len(list(d.glob("*.png"))) if d.is_dir() else 0


def manifest(run: Path) -> dict:
    return json.loads((run / "manifest.json").read_text())


def counts_are_true(run: Path) -> None:
    """The manifest never counts a frame that is not on disk."""
    for v in manifest(run)["views"]:
        assert v["frames"] == frames_on_disk(run, v["index"]), (v, frames_on_disk(run, v["index"]))
        if v["complete"]:
            assert v["frames"] == len(manifest(run)["frame_names"])


def only_run(out: Path) -> Path:
    runs = [p for p in out.iterdir() if p.is_dir()]
    assert len(runs) == 1, runs
    return runs[0]


# ---- a full disk, in process --------------------------------------------------------------------

class _LimitedFile:
    """A file object whose writes draw on a :class:`FullDisk`'s budget."""

    def __init__(self, f: Any, disk: "FullDisk", path: str) -> None:
        self._f, self._disk, self._path = f, disk, path

    def write(self, data: bytes) -> int:
        if len(data) > self._disk.free:
            self._disk.refused.append(self._path)
            raise OSError(self._disk.errno, os.strerror(self._disk.errno))
        self._disk.free -= len(data)
        return self._f.write(data)

    def __enter__(self) -> "_LimitedFile":
        return self

    def __exit__(self, *exc: Any) -> None:
        self._f.close()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._f, name)


class FullDisk:
    """The directory ``root`` has ``free`` bytes left for dotshell's files (see the module
    docstring): writes through ``os.fdopen`` and ``open`` (frame stacks) draw on it; a file deleted (``os.unlink``) or
    replaced (``os.replace``) under ``root`` gives its bytes back, as on a real disk.
    ``refused`` lists the files whose write failed."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, root: Path, free: int,
                 error: int = errno.ENOSPC) -> None:
        self.root, self.free, self.errno = str(root), free, error
        self.refused: list[str] = []
        real_fdopen, real_unlink, real_replace = os.fdopen, os.unlink, os.replace
        real_open = builtins.open

        def open_(file: Any, mode: str = "r", *args: Any, **kwargs: Any) -> Any:
            f = real_open(file, mode, *args, **kwargs)
            if isinstance(file, (str, os.PathLike)) and ("w" in mode or "a" in mode) \
                    and os.path.abspath(os.fspath(file)).startswith(self.root):
                return _LimitedFile(f, self, os.fspath(file))
            return f

        def fdopen(fd: int, mode: str = "r", *args: Any, **kwargs: Any) -> Any:
            f = real_fdopen(fd, mode, *args, **kwargs)
            path = os.readlink(f"/proc/self/fd/{fd}")
            if ("w" in mode or "a" in mode) and path.startswith(self.root):
                return _LimitedFile(f, self, path)
            return f

        def give_back(path: Any) -> None:
            p = os.fspath(path)
            if os.path.abspath(p).startswith(self.root) and os.path.isfile(p):
                self.free += os.path.getsize(p)

        def unlink(path: Any, *args: Any, **kwargs: Any) -> None:
            give_back(path)
            real_unlink(path, *args, **kwargs)

        def replace(src: Any, dst: Any, *args: Any, **kwargs: Any) -> None:
            give_back(dst)
            real_replace(src, dst, *args, **kwargs)

        monkeypatch.setattr(os, "fdopen", fdopen)
        monkeypatch.setattr(builtins, "open", open_)
        monkeypatch.setattr(os, "unlink", unlink)
        monkeypatch.setattr(os, "remove", unlink)
        monkeypatch.setattr(os, "replace", replace)


# ---- a real file system in a private mount namespace ---------------------------------------------

def tmpfs_available() -> bool:
    if shutil.which("unshare") is None:
        return False
    probe = subprocess.run(["unshare", "-rm", "sh", "-c", "mount -t tmpfs -o size=8k tmpfs /mnt"],
                           capture_output=True)
    return probe.returncode == 0


needs_tmpfs = pytest.mark.skipif(not tmpfs_available(), reason="cannot mount a private tmpfs "
                                 "here (no user/mount namespaces)")

#: Runs inside the namespace: the steps (dotshell commands, or ``["!", shell command]``), then
#: what the runs look like (JSON).
_INSIDE = r"""
import json, subprocess, sys
from pathlib import Path
sys.path.insert(0, TESTS)
from dotshell.cli.app import main
from fault_harness import frames_on_disk
out, steps = Path(sys.argv[1]), json.loads(sys.argv[2])
code = None
for step in steps:
    runs = sorted(str(p.parent) for p in out.rglob("manifest.json"))
    step = [a.replace("{run}", runs[0] if runs else "") for a in step]
    if step[0] == "!":
        subprocess.run(step[1], shell=True, check=True)
    else:
        code = main(step)
report = {"code": code, "runs": []}
for m in sorted(out.rglob("manifest.json")):
    run = m.parent
    manifest = json.loads(m.read_text())
    views = {f"view_{v['index']:03d}": frames_on_disk(run, v["index"]) for v in manifest["views"]}
    report["runs"].append({"manifest": manifest, "frames": views,
                           "tmp": [str(p) for p in run.rglob(".*.tmp")]})
print("REPORT " + json.dumps(report))
"""


def in_tmpfs(mount: Path, options: str, steps: list[list[str]]) -> tuple[dict, str]:
    """Run ``steps`` — dotshell argument lists (``{run}`` = the run made so far) or
    ``["!", shell command]`` — in one process with a fresh tmpfs (mount ``options``) at
    ``mount``, in a private mount namespace. Returns (report of the runs, stderr); the report's
    ``code`` is the last command's exit code."""
    mount.mkdir(parents=True, exist_ok=True)
    script = mount.parent / "inside.py"
    script.write_text(_INSIDE.replace("TESTS", repr(str(Path(__file__).parent)), 1))
    inner = (f"mount -t tmpfs -o {options} tmpfs {shlex.quote(str(mount))} && "
             f"{shlex.quote(sys.executable)} {shlex.quote(str(script))} "
             f"{shlex.quote(str(mount))} {shlex.quote(json.dumps(steps))}")
    proc = subprocess.run(["unshare", "-rm", "sh", "-c", inner], capture_output=True, text=True,
                          cwd=ROOT, timeout=300)
    line = next((ln for ln in proc.stdout.splitlines() if ln.startswith("REPORT ")), None)
    assert line is not None, proc.stderr[-3000:]
    return json.loads(line[len("REPORT "):]), proc.stderr
