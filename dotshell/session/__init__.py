"""The session: one live profile, its rig and its last run, and the scripting facade front ends
and user scripts drive (:class:`dotshell.session.console.Session`)."""
