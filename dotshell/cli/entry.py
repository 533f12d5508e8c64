"""The ``dotshell`` command's entry point: answers ``dotshell --version`` before anything heavy
is imported (rich, pluggy, numpy), and hands every other command to :func:`dotshell.cli.app.main`.

``--version`` alone took ~0.2 s of wall time through :mod:`dotshell.cli.app`, whose imports (rich's
console and progress bars, the event types, pluggy) are most of a bare command's start; here
it costs the interpreter's start and this module.
"""

from __future__ import annotations

import sys


def main(argv: list[str] | None = None) -> int:
    """``dotshell`` on ``argv`` (``sys.argv[1:]`` when None); its exit status."""
    args = sys.argv[1:] if argv is None else argv
    if args == ["--version"]:
        from dotshell import __version__

        sys.stdout.write(f"dotshell {__version__}\n")
        return 0
    from dotshell.cli.app import main as cli_main

    return cli_main(argv)


if __name__ == "__main__":
    sys.exit(main())
