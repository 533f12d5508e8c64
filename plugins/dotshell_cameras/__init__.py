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

harvesters and pylablib are imported only when such a camera connects.
"""

from __future__ import annotations

from typing import Any

from dotshell import hookimpl
from dotshell.backends import Backend, RigContext
from dotshell_cameras.genicam import SETTINGS_SCHEMA as GENICAM_SCHEMA
from dotshell_cameras.genicam import GenICamCamera
from dotshell_cameras.opencv import SETTINGS_SCHEMA as OPENCV_SCHEMA
from dotshell_cameras.opencv import OpenCVCamera
from dotshell_cameras.scientific import SETTINGS_SCHEMA as SCIENTIFIC_SCHEMA
from dotshell_cameras.scientific import ScientificCamera


def _base(context: RigContext | None) -> str:
    return context.base_dir if context is not None else "."


@hookimpl
def dotshell_cameras() -> list[Backend]:
    return [
        Backend("opencv", lambda settings, context: OpenCVCamera(settings, _base(context)),
                OPENCV_SCHEMA, "any source cv2.VideoCapture opens: UVC/V4L2 cameras, video "
                "files, image sequences; exposure mapped per capture API"),
        Backend("genicam", lambda settings, context: GenICamCamera(settings, _base(context)),
                GENICAM_SCHEMA, "GenICam cameras through harvesters and a GenTL producer "
                "(extra dotshell[genicam]); hardware trigger"),
        Backend("scientific", lambda settings, context: ScientificCamera(settings),
                SCIENTIFIC_SCHEMA, "EMCCD/sCMOS cameras through pylablib (extra "
                "dotshell[pylablib]): EM gain, cooling, ROI, binning, trigger"),
    ]


__all__: list[Any] = ["GenICamCamera", "OpenCVCamera", "ScientificCamera"]
