"""Example third-party dotshell plugin: an exporter writing a run's merged cloud as ``cloud.xyz``.

Its backend is declared in ``dotshell.toml`` (package data, see pyproject.toml): dotshell lists
it without importing this package and imports :mod:`dotshell_xyz_export.exporter` only when a
profile enables it::

    [export.xyz-text]
    delimiter = ","
    decimals = 4
"""
