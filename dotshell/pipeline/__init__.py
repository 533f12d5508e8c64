"""Workflow stages: acquire → reconstruct (per view) → merge → validate, each reading and
writing the run directory. :mod:`dotshell.pipeline.scan` strings them together."""
