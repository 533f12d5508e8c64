"""Imports that need help on some machines."""

from __future__ import annotations

import ctypes
from types import ModuleType

from dotshell.errors import DotshellError


def import_open3d() -> ModuleType:
    """Import open3d after loading ``libusb-1.0`` from the ``libusb-package`` wheel: open3d
    0.18+ links against it and most servers have no system copy. The same library serves
    pyusb as its backend."""
    try:
        import libusb_package

        path = libusb_package.get_library_path()
        if path:
            ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)
    except (ImportError, OSError):
        pass  # fall through: a system libusb may still satisfy open3d
    try:
        import open3d
    except (ImportError, OSError) as exc:
        raise DotshellError(f"open3d cannot be imported ({exc}). Install open3d and "
                            "libusb-package into this Python environment (`python -m pip install "
                            "open3d libusb-package`, or reinstall dotshell, which depends on both; "
                            "in a checkout, `make demo`), or install the system's libusb-1.0 "
                            "(e.g. `apt install libusb-1.0-0`).") from None
    return open3d
