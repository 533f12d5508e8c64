"""One widget (or screen) per module; see :mod:`dotshell.tui.app` for how they are composed."""
