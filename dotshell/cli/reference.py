"""The command reference as Markdown, generated from the ``dotshell`` argparse parser (the docs
site's ``cli.md``, built by ``mkdocs_hooks.py``): every command, its usage, arguments and
options with their help, defaults and choices — the same text ``dotshell COMMAND --help``
prints, so the two cannot disagree."""

from __future__ import annotations

import argparse


def _subparsers(parser: argparse.ArgumentParser) -> argparse._SubParsersAction | None:
    return next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)


def _cell(text: str) -> str:
    return " ".join(text.split()).replace("|", "\\|")


def _arguments(parser: argparse.ArgumentParser) -> list[str]:
    rows = []
    for a in parser._actions:
        if isinstance(a, (argparse._HelpAction, argparse._SubParsersAction)) or \
                a.help == argparse.SUPPRESS:
            continue
        name = ", ".join(f"`{o}`" for o in a.option_strings) or f"`{a.metavar or a.dest}`"
        if a.option_strings and a.nargs != 0:
            name += f" `{a.metavar or a.dest.upper()}`"
        extra = []
        if a.choices:
            extra.append("one of " + ", ".join(f"`{c}`" for c in a.choices))
        if a.option_strings and a.default not in (None, False, [], argparse.SUPPRESS) and \
                a.nargs != 0 and "default" not in (a.help or ""):
            extra.append(f"default `{a.default}`")
        help_text = (a.help or "") % {"default": a.default} if a.help else ""
        rows.append(f"| {name} | {_cell(help_text)}{' (' + '; '.join(extra) + ')' if extra else ''} |")
    if not rows:
        return []
    return ["| argument | meaning |", "|---|---|", *rows, ""]


def _section(parser: argparse.ArgumentParser, title: str, help_text: str, depth: int,
             child_depth: int | None = None) -> list[str]:
    lines = [f"{'#' * depth} {title}", ""]
    if help_text:
        lines += [_cell(help_text[0].upper() + help_text[1:]) + ".", ""]
    usage = " ".join(parser.format_usage().replace("usage: ", "", 1).split())
    lines += ["```", usage, "```", ""]
    if parser.description and depth > 1:
        lines += [_cell(parser.description), ""]
    lines += _arguments(parser)
    sub = _subparsers(parser)
    if sub is not None:
        helps = {a.dest: a.help or "" for a in sub._choices_actions}
        for name, child in sub.choices.items():
            lines += _section(child, f"{title} {name}", helps.get(name, ""),
                              child_depth or min(depth + 1, 4))
    return lines


def markdown(parser: argparse.ArgumentParser) -> str:
    """The reference of ``parser`` and every sub-command as Markdown."""
    return "\n".join(_section(parser, parser.prog, "", 2, child_depth=2)) + "\n"
