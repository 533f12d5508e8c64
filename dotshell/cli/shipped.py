"""``dotshell profiles`` (list the shipped profiles and layouts, copy one out to edit) and
``dotshell docs`` (where the installed documentation is). The files are in
:mod:`dotshell.shipped`."""

from __future__ import annotations

import argparse
import shutil
import tomllib
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.markup import escape
from rich.table import Table

from dotshell.cli.common import print_as_is
from dotshell.errors import DotshellError
from dotshell.shipped import KINDS, shipped_dir, shipped_file, shipped_names, unknown_hint

out = Console(highlight=False)


def _description(path: Path) -> str:
    """The ``description`` of a profile's ``[profile]`` or a layout's ``[layout]`` table."""
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        return f"(unreadable: {exc})"
    table = raw.get("profile") or raw.get("layout") or {}
    return str(table.get("description", ""))


def cmd_profiles(args: argparse.Namespace) -> int:
    if args.profiles_command == "copy":
        return cmd_copy(args)
    for kind in KINDS:
        t = Table(title=f"shipped {kind} (use the bare name, e.g. `dotshell "
                        f"{'scan' if kind == 'profiles' else 'decode --layout'} NAME`)")
        t.add_column("name")
        t.add_column("description")
        for name in shipped_names(kind):
            t.add_row(name, escape(_description(shipped_dir(kind) / f"{name}.toml")))
        out.print(t)
        print_as_is(out, f"in {shipped_dir(kind).resolve()}")
    out.print("copy one out to edit: dotshell profiles copy NAME my-rig.toml")
    return 0


def _find(name: str) -> Path:
    """The shipped profile or layout of that name (profiles first)."""
    for kind in KINDS:
        path = shipped_file(kind, name)
        if path is not None:
            return path
    raise DotshellError(f"no shipped profile or layout is named {name}. "
                        f"{unknown_hint('profiles')} Layouts: {', '.join(shipped_names('layouts'))}.")


def referenced_files(raw: Any, base: Path) -> list[str]:
    """Relative paths in a parsed TOML (strings and lists of strings at any depth) that name a
    file under ``base``: the files a copied profile needs beside it (e.g. a LightCrafter
    profile's flash images)."""
    found: list[str] = []
    if isinstance(raw, dict):
        for value in raw.values():
            found += referenced_files(value, base)
    elif isinstance(raw, list):
        for value in raw:
            found += referenced_files(value, base)
    elif (isinstance(raw, str) and raw and not Path(raw).is_absolute() and ".." not in raw
          and (base / raw).is_file()):
        found.append(raw)
    return found


def cmd_copy(args: argparse.Namespace) -> int:
    """Copy a shipped profile or layout (and the files it names relative to itself) to DEST."""
    src = _find(args.name)
    dest = Path(args.dest).expanduser()
    if dest.is_dir():
        dest = dest / src.name
    if dest.suffix != ".toml":
        raise DotshellError(f"{dest}: give a destination ending in .toml, e.g. my-rig.toml.")
    extras = referenced_files(tomllib.loads(src.read_text(encoding="utf-8")), src.parent)
    targets = [dest, *(dest.parent / rel for rel in extras)]
    existing = [str(p) for p in targets if p.exists()]
    if existing and not args.force:
        raise DotshellError(f"{', '.join(existing)} exist already; choose another destination "
                            "or add --force to overwrite.")
    dest.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, dest)
    for rel in extras:
        (dest.parent / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(src.parent / rel, dest.parent / rel)
    print_as_is(out, f"copied {src.name} to {dest}" +
                (f" with {', '.join(extras)}" if extras else ""))
    verb = "scan" if src.parent.name == "profiles" else "decode --captures DIR --layout"
    print_as_is(out, f"edit it, then: dotshell {verb} {dest}")
    return 0


def docs_paths() -> tuple[Path, Path | None]:
    """The installed documentation (Markdown) and the built site's index.html, if one was built
    in this checkout (``mkdocs build`` writes ``site/``)."""
    docs = shipped_dir("docs").resolve()
    site = docs.parent / "site" / "index.html"
    return docs, (site if site.is_file() else None)


def cmd_docs(args: argparse.Namespace) -> int:
    docs, site = docs_paths()
    if not (docs / "index.md").is_file():
        raise DotshellError(f"the documentation is not installed with this dotshell ({docs} has "
                            "no index.md); reinstall dotshell from its wheel.")
    print_as_is(out, f"documentation: {docs}  (start with {docs / 'index.md'})")
    if site is not None:
        print_as_is(out, f"built site: {site}")
    return 0


def add_shipped_parsers(sub: Any) -> None:
    """``profiles`` (with ``copy``) and ``docs``."""
    sp = sub.add_parser("profiles", help="list the shipped profiles and layouts; `profiles copy "
                        "NAME DEST.toml` copies one out to edit")
    copy_sub = sp.add_subparsers(dest="profiles_command", metavar="copy")
    cp = copy_sub.add_parser("copy", help="copy a shipped profile or layout to edit it")
    cp.add_argument("name", help="name of a shipped profile or layout (see `dotshell profiles`)")
    cp.add_argument("dest", help="destination file (.toml) or directory")
    cp.add_argument("--force", action="store_true", help="overwrite existing files")
    sp.set_defaults(func=cmd_profiles)
    sp = sub.add_parser("docs", help="print where the installed documentation is")
    sp.set_defaults(func=cmd_docs)
