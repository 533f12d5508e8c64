"""The Textual terminal UI (``dotshell tui``): rig, scan, preview, log and a Python console, a
front end of a rig server (:mod:`dotshell.server`) that holds the session. Widgets only show
state and forward keys as requests to the server; requests run in worker threads and what the
server pushes arrives as messages."""
