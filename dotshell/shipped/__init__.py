"""The files that ship inside dotshell: ready-to-run profiles, layout files and the docs.

In the repository ``dotshell/shipped/profiles``, ``layouts`` and ``docs`` are symbolic links to
the top-level ``profiles/``, ``layouts/`` and ``docs/`` (the source, edited there); a wheel carries
their files as package data (``[tool.setuptools.package-data]`` in pyproject.toml), so an
installed dotshell finds them here, and so does an editable install through the links.

A bare name (``sim-metal-cylinder``, with or without ``.toml``) that is not a file of that path
means the shipped file of that name: a user's file always wins.
"""

from __future__ import annotations

from pathlib import Path

#: The kinds of shipped files that are looked up by name.
KINDS = ("profiles", "layouts")

COPY_HINT = ("`dotshell profiles` lists them; `dotshell profiles copy NAME my-rig.toml` copies one "
             "out to edit.")


def shipped_dir(kind: str) -> Path:
    """The directory of a kind of shipped files (``profiles``, ``layouts`` or ``docs``)."""
    return Path(__file__).parent / kind


def shipped_names(kind: str) -> list[str]:
    """The names (file stems) of the shipped TOML files of ``kind``, sorted."""
    return sorted(p.stem for p in shipped_dir(kind).glob("*.toml"))


def shipped_file(kind: str, name: str) -> Path | None:
    """The shipped file of that name (``NAME`` or ``NAME.toml``), or None."""
    if not name or "/" in name or name.startswith("."):
        return None
    path = shipped_dir(kind) / (name if name.endswith(".toml") else f"{name}.toml")
    return path if path.is_file() else None


def is_bare_name(name_or_path: str | Path) -> bool:
    """True for a name without a directory part (``sim-metal-cylinder``, ``x.toml``)."""
    text = str(name_or_path)
    return bool(text) and "/" not in text and text not in (".", "..")


def resolve(kind: str, name_or_path: str | Path) -> Path:
    """The file meant by ``name_or_path``: that path when it is a file, else the shipped file of
    that bare name, else the path unchanged (the caller's error names it and
    :func:`unknown_hint`)."""
    path = Path(name_or_path).expanduser()
    if path.is_file() or not is_bare_name(name_or_path):
        return path
    return shipped_file(kind, str(name_or_path)) or path


def unknown_hint(kind: str) -> str:
    """The sentence an error about an unknown profile or layout ends with."""
    names = shipped_names(kind)
    what = kind[:-1]
    listed = ", ".join(names) if names else "none (this installation ships none)"
    return f"Give a {what} TOML file or the name of one of the shipped {kind}: {listed}. {COPY_HINT}"
