"""dotshell — instrument shell for structured-light surface scanning on DOT rigs."""

import pluggy

__version__ = "0.1.0"

#: Decorator for plugin hook implementations: ``@dotshell.hookimpl``.
hookimpl = pluggy.HookimplMarker("dotshell")
