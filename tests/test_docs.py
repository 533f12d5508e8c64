"""Docs stay true: every profile key and every command is documented."""

from pathlib import Path

from dotshell.cli.app import build_parser
from dotshell.profile.loader import SCHEMA

ROOT = Path(__file__).resolve().parents[1]


def _keys(schema, prefix=""):
    for name, s in schema.items():
        yield prefix + name, name
        if s.kind == "table" and s.schema and name not in ("camera", "projector", "stage",
                                                           "analyzer", "light_source", "coding"):
            yield from _keys(s.schema, prefix + name + ".")


def test_every_profile_key_is_in_docs_profiles():
    text = (ROOT / "docs" / "profiles.md").read_text()
    missing = [full for full, name in _keys(SCHEMA) if f"`{name}`" not in text
               and f"[{full}]" not in text]
    assert missing == []


def test_every_command_is_in_readme():
    readme = (ROOT / "README.md").read_text()
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert [c for c in sub.choices if f"dotshell {c}" not in readme] == []
