"""The rig server: one :class:`~dotshell.session.console.Session` (rig, scans, console namespace, event
log) held by a background process whose session worker process owns the devices. Front
ends — ``dotshell tui``, ``attach``, ``status``, ``scan --detach``, ``stop`` — talk to it over a Unix-domain socket in the
user's runtime directory and receive the events ``events.jsonl`` records, so a front end that
dies (a dropped SSH session) takes nothing with it. The wire format is in docs/server.md.

Modules: :mod:`.paths` (where sockets, logs and the user config live), :mod:`.protocol` (the
wire format), :mod:`.server` (the process clients talk to), :mod:`.worker` (the process that
holds the session: plugins, rig, scan, console), :mod:`.supervisor` (the server's side of it:
mirror, requests, the hang watch, ending and restarting it), :mod:`.callboard` (the device
calls in progress, readable while the worker hangs), :mod:`.commands` (what each request does),
:mod:`.repl` (the Python console run inside the worker), :mod:`.client` (the front ends'
side), :mod:`.launch` (starting a detached server), :mod:`.progress` and :mod:`.describe`
(scan progress and event lines as people read them).
"""
