"""The rig: devices built from a profile (``assembly``), the handles that guard every call
(``handles``), rig checks, serial-port discovery and device ownership."""

from dotshell.runtime.moved import forward_to

__getattr__ = forward_to(__name__)
