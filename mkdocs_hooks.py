"""mkdocs hooks (mkdocs.yml ``hooks:``): the command reference generated from the parser into
``cli.md`` below its marker, and the changelog page from CHANGELOG.md. Nothing is fetched."""

from __future__ import annotations

from pathlib import Path

from mkdocs.structure.files import File

MARKER = "<!-- the command reference is generated here from the parser -->"


def on_files(files, config):
    """Add ``changelog.md`` from the repository's CHANGELOG.md."""
    text = (Path(config["config_file_path"]).parent / "CHANGELOG.md").read_text(encoding="utf-8")
    files.append(File.generated(config, "changelog.md", content=text))
    return files


def on_page_markdown(markdown, page, config, files):
    """Fill ``cli.md``'s marker with the reference of ``dotshell`` and every command."""
    if page.file.src_uri != "cli.md":
        return markdown
    if MARKER not in markdown:
        raise ValueError(f"docs/cli.md lost its marker {MARKER!r}")
    from dotshell.cli import build_parser
    from dotshell.cli_reference import markdown as reference

    return markdown.replace(MARKER, reference(build_parser()))
