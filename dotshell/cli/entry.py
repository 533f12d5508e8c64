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
    if _runs_the_mesher(args):
        # the mesh process imports the meshers (~0.6 s of CPU) on the other core while this
        # one imports the CLI and parses (~0.15-0.2 s of `dotshell mesh`'s wall time, issue 32);
        # `cmd_mesh` takes it, or ends it when the command fails before a job
        from dotshell.pipeline import mesh_process

        mesh_process.start_early()
        try:
            return _cli_main(argv)
        finally:
            mesh_process.discard_early()
    return _cli_main(argv)


def _cli_main(argv: list[str] | None) -> int:
    from dotshell.cli.app import main as cli_main

    return cli_main(argv)


def _runs_the_mesher(args: list[str]) -> bool:
    """Whether ``args`` are a ``dotshell mesh`` that will mesh (not its help)."""
    return args[:1] == ["mesh"] and not {"-h", "--help"} & set(args)


if __name__ == "__main__":
    sys.exit(main())
