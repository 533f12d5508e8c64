"""Process set-up: threads and malloc (``process``), huge pages, the thread pool, the numba
cache, library compatibility, directories (``paths``) and old import paths (``moved``)."""

from dotshell.runtime.moved import forward_to

__getattr__ = forward_to(__name__)
