"""``dotshell frames RUN``: list a run's stored frames, or export them as PNG files to look at
(thin: calls :mod:`dotshell.run.frames` through :class:`~dotshell.run.store.RunStore`)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from rich.console import Console
from rich.markup import escape
from rich.table import Table

from dotshell.cli.common import print_as_is
from dotshell.errors import RunError

if TYPE_CHECKING:  # the frame readers (tifffile, cv2, numpy) load when the command runs
    from dotshell.run.store import RunStore

out = Console(highlight=False)


def _size_mb(path: Path) -> float:
    files = [path] if path.is_file() else list(path.glob("*")) if path.is_dir() else []
    return sum(p.stat().st_size for p in files) / 1e6


def _views(store: RunStore, wanted: list[int] | None) -> list[int]:
    n = len(store.manifest["views"])
    bad = [v for v in wanted or [] if not 0 <= v < n]
    if bad:
        raise RunError(f"{store.root} has views 0-{n - 1}; there is no view "
                       f"{', '.join(map(str, bad))}.")
    return wanted if wanted else list(range(n))


def cmd_frames(args: argparse.Namespace) -> int:
    from dotshell.run.frames import export_png
    from dotshell.run.store import RunStore

    store = RunStore.open(Path(args.run))
    manifest = store.manifest
    views = _views(store, args.view)
    if args.png:
        total = 0
        for v in views:
            total += len(export_png(store.frames(v), Path(args.png)))
        print_as_is(out, f"{total} frames of {len(views)} view(s) written as PNG under "
                         f"{args.png}/view_NNN/")
        return 0
    t = Table(title=f"{escape(str(store.root))}: frames ({manifest.get('frame_format', 'png/1')},"
                    f" {len(manifest['frame_names'])} per view)")
    for col in ("view", "angle [deg]", "frames on disk", "complete", "size [MB]", "file"):
        t.add_column(col)
    for v in views:
        entry, frames = manifest["views"][v], store.frames(v)
        t.add_row(str(v), f"{entry['angle_deg']:g}", str(frames.count()),
                  "yes" if entry["complete"] else "no", f"{_size_mb(frames.path):.1f}",
                  escape(str(frames.path.relative_to(store.root))))
    out.print(t)
    return 0


def add_frames_parser(sub) -> None:
    """Add the ``frames`` sub-command."""
    sp = sub.add_parser("frames", help="list a run's stored frames, or export them as PNG files")
    sp.add_argument("run", help="run directory")
    sp.add_argument("--view", type=int, action="append", metavar="N",
                    help="only this view (repeatable; default: all views)")
    sp.add_argument("--png", metavar="DIR", help="write the frames losslessly as "
                    "DIR/view_NNN/III_NAME.png (8 or 16 bit, as captured)")
    sp.set_defaults(func=cmd_frames)
