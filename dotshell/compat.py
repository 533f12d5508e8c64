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
        raise DotshellError(f"open3d cannot be imported ({exc}). Reinstall with `make demo` "
                            "(it installs open3d and libusb-package).") from None
    return open3d
