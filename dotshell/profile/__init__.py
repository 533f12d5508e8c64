"""Profiles: the TOML file, validated (``loader``), and the schemas of its sections
(``calibration``, ``mesh``, ``transillum``)."""

from dotshell.runtime.moved import forward_to

__getattr__ = forward_to(__name__)
