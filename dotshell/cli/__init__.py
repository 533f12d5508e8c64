"""The command line: ``entry`` (the console script, fast for ``--version``), ``app`` (the parser
and dispatch), ``common`` (printing, progress, the plugin manager from the arguments) and one
module per command family. Nothing outside ``cli/`` imports from it."""

import os

from dotshell.runtime.moved import forward_to

__getattr__ = forward_to(__name__)

# The command runs BLAS on one thread (dotshell.runtime.process.configure_process), but
# OpenBLAS also allocates a buffer for each of its threads when numpy loads it: under an
# address-space limit (`ulimit -v 700000`) that failed before the command could say a word
# ("OpenBLAS error: Memory allocation still failed", exit 1; issue 33). Set before numpy is
# imported, it loads for one thread; a user's own setting is kept.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
