"""The Textual terminal UI (``dotshell tui``): rig, scan, preview, log and a Python console over
one :class:`dotshell.console.Session`. Widgets only show state and forward keys to the session;
device I/O, scans and console input run in worker threads and report through messages."""
