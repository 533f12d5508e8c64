"""``python -m dotshell``: the ``dotshell`` command."""

import sys

from dotshell.cli.entry import main

if __name__ == "__main__":
    sys.exit(main())
