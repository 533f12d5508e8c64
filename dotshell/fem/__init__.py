"""Finite-element meshes for the light model: mesh types and measures (``meshes``), compiled
loops (``kernels``), the diffusion forward model (``forward``), optical properties
(``optics``) and mesh files (``meshfiles``)."""

from dotshell.runtime.moved import forward_to

__getattr__ = forward_to(__name__)
