"""dotshell_cameras — real cameras: anything OpenCV opens, GenICam cameras through harvesters,
scientific cameras through pylablib.

Registered under the ``dotshell`` entry-point group as ``cameras = "dotshell_cameras"``.
Backends (docs/hardware.md):

* ``opencv`` — UVC / V4L2 cameras, DirectShow / Media Foundation, video files and image
  sequences (a recorded scan replays through it);
* ``genicam`` — GigE Vision / USB3 Vision cameras through a GenTL producer (extra
  ``dotshell[genicam]``), with a hardware trigger input;
* ``scientific`` — Andor, Hamamatsu DCAM, PCO, Thorlabs, IDS uc480 through pylablib (extra
  ``dotshell[pylablib]``): EM gain, cooling, ROI, binning, external trigger.

harvesters and pylablib are imported only when such a camera connects. The backends are declared
in ``dotshell.toml`` and built in :mod:`dotshell_cameras.backends`: this module imports no
driver (the names below are imported on first access).
"""

from __future__ import annotations

from dotshell import hookimpl
from dotshell.backends import Backend
from dotshell.manifest import backends_of, lazy_exports

__all__ = ["GenICamCamera", "OpenCVCamera", "ScientificCamera"]
__getattr__ = lazy_exports(__name__, {"GenICamCamera": "genicam:GenICamCamera",
                                      "OpenCVCamera": "opencv:OpenCVCamera",
                                      "ScientificCamera": "scientific:ScientificCamera"})


@hookimpl
def dotshell_cameras() -> list[Backend]:
    """All cameras, imported (when this package is registered as a plain pluggy plugin)."""
    return backends_of(__name__, "camera")
