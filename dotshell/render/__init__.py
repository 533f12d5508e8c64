"""Off-screen previews written as PNG: frames, code maps and clouds (``previews``), meshes
(``mesh_previews``)."""

from dotshell.runtime.moved import forward_to

__getattr__ = forward_to(__name__)
