"""Profiles: the TOML file, validated (``loader``), its core sections as typed objects
(``sections``: ``ScanSettings``, ...), and the schemas of its sections (``calibration``,
``mesh``, ``transillum``)."""

from dotshell.runtime.moved import forward_to

__getattr__ = forward_to(__name__)
