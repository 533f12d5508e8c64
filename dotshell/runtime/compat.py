"""Imports that need help on some machines, or cost more than dotshell uses of them."""

from __future__ import annotations

import ctypes
import importlib.util
import sys
from pathlib import Path
from types import ModuleType
from typing import Any, Callable

from dotshell.errors import DotshellError

#: open3d's plotly drawing and its dash web server (``open3d.visualization.draw_plotly``).
#: ``import open3d`` imports it unconditionally (open3d/visualization/__init__.py, 0.18-0.20;
#: no setting turns it off) and with it dash and plotly: ~0.35 s of CPU, 38 MiB and 670 modules
#: in every process that imports open3d (measured alone: 0.75 -> 0.39 s, 208 -> 170 MiB), and
#: dotshell draws nothing with it.
#: :func:`import_open3d` puts a :class:`DeferredModule` in its place before open3d is imported.
OPEN3D_WEB_DRAWING = "open3d.visualization.draw_plotly"


class DeferredModule(ModuleType):
    """Stands in for a module that is imported only when one of its functions is called.

    ``from module import name`` gets a function that imports the real module (its source
    file ``path``, under its own name, replacing this stand-in in :data:`sys.modules`) at its
    first call and calls the real ``name`` with the same arguments. Names beginning with an
    underscore are not forwarded (they are how tools probe modules)."""

    def __init__(self, name: str, path: Path) -> None:
        super().__init__(name, f"Stands in for {name} (imported at first use; "
                               "dotshell.runtime.compat).")
        self._deferred_path = path
        self._real: ModuleType | None = None

    def __getattr__(self, attr: str) -> Callable[..., Any]:
        if attr.startswith("_"):
            raise AttributeError(attr)

        def forward(*args: Any, **kwargs: Any) -> Any:
            return getattr(self.real_module(), attr)(*args, **kwargs)

        forward.__name__ = forward.__qualname__ = attr
        return forward

    def real_module(self) -> ModuleType:
        """The real module, imported at the first call."""
        if self._real is None:
            spec = importlib.util.spec_from_file_location(self.__name__, self._deferred_path)
            assert spec is not None and spec.loader is not None
            real = importlib.util.module_from_spec(spec)
            sys.modules[self.__name__] = real
            try:
                spec.loader.exec_module(real)
            except BaseException:
                sys.modules[self.__name__] = self
                raise
            self._real = real
        return self._real


def _defer_open3d_web_drawing() -> None:
    """A :class:`DeferredModule` for :data:`OPEN3D_WEB_DRAWING`, when open3d is about to be
    imported for the first time in this process and the module is where open3d 0.18-0.20 keep
    it (otherwise nothing: open3d imports as it would)."""
    if "open3d" in sys.modules or OPEN3D_WEB_DRAWING in sys.modules:
        return
    spec = importlib.util.find_spec("open3d")  # the package's location; runs none of its code
    if spec is None or spec.origin is None:
        return
    path = Path(spec.origin).parent / "visualization" / "draw_plotly.py"
    if path.is_file():
        sys.modules[OPEN3D_WEB_DRAWING] = DeferredModule(OPEN3D_WEB_DRAWING, path)


def import_open3d() -> ModuleType:
    """Import open3d after loading ``libusb-1.0`` from the ``libusb-package`` wheel: open3d
    0.18+ links against it and most servers have no system copy. The same library serves
    pyusb as its backend. open3d's plotly drawing (dash, plotly) is imported when first used
    (:data:`OPEN3D_WEB_DRAWING`)."""
    try:
        import libusb_package

        path = libusb_package.get_library_path()
        if path:
            ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)
    except (ImportError, OSError):
        pass  # fall through: a system libusb may still satisfy open3d
    _defer_open3d_web_drawing()
    try:
        import open3d
    except (ImportError, OSError) as exc:
        if isinstance(sys.modules.get(OPEN3D_WEB_DRAWING), DeferredModule):
            del sys.modules[OPEN3D_WEB_DRAWING]
        raise DotshellError(f"open3d cannot be imported ({exc}). Install open3d and "
                            "libusb-package into this Python environment (`python -m pip install "
                            "open3d libusb-package`, or reinstall dotshell, which depends on both; "
                            "in a checkout, `make demo`), or install the system's libusb-1.0 "
                            "(e.g. `apt install libusb-1.0-0`).") from None
    return open3d
