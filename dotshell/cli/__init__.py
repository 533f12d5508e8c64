"""The command line: ``entry`` (the console script, fast for ``--version``), ``app`` (the parser
and dispatch), ``common`` (printing, progress, the plugin manager from the arguments) and one
module per command family. Nothing outside ``cli/`` imports from it."""

from dotshell.runtime.moved import forward_to

__getattr__ = forward_to(__name__)
