"""The profile's ``[calibrate]`` section: the target and the poses to capture it in."""

from __future__ import annotations

from dotshell.settings import Setting

#: ``[calibrate]`` keys (see docs/calibration.md and docs/profiles.md).
CALIBRATE_SCHEMA: dict[str, Setting] = {
    "target": Setting("str", default="checkerboard", choices=("checkerboard", "charuco"),
                      help="printed planar target"),
    "columns": Setting("int", default=11, min=3, help="squares across the board"),
    "rows": Setting("int", default=8, min=3, help="squares down the board"),
    "square_mm": Setting("float", default=3.0, min=0.01, unit="mm", help="side of a square"),
    "marker_mm": Setting("float", default=2.2, min=0.01, unit="mm",
                         help="ChArUco marker side (charuco only)"),
    "dictionary": Setting("str", default="DICT_4X4_50",
                          help="ArUco dictionary of the ChArUco markers (cv2.aruco name)"),
    "exposure_ms": Setting("float", default=10.0, min=0.001, unit="ms",
                           help="camera exposure for the target frames"),
    "distortion": Setting("str", default="auto",
                          choices=("auto", "k1", "k1k2", "k1k2k3", "k1k2p1p2", "full"),
                          help="lens model solved for: auto (each lens's model chosen by "
                               "held-out poses, docs/calibration.md) | k1 | k1 k2 | k1 k2 k3 | "
                               "k1 k2 p1 p2 | full = k1 k2 p1 p2 k3"),
    "min_poses": Setting("int", default=4, min=3,
                         help="fewest good poses a solve accepts (a solve from few poses is "
                              "still refused when its uncertainty exceeds max_sigma_pct)"),
    "outlier_factor": Setting("float", default=3.0, min=1.0,
                              help="a pose whose RMS exceeds this many times the median "
                                   "(and max_rms_px / 4) is left out"),
    "max_rms_px": Setting("float", default=1.0, min=0.01, unit="px",
                          help="a pose whose reprojection RMS exceeds this is left out; a "
                               "solve (camera, projector, joint, turntable axis) whose RMS "
                               "exceeds it is refused and nothing is written"),
    "max_sigma_pct": Setting("float", default=1.0, min=0.0001, unit="%",
                             help="a solve is refused (nothing written) when the one-sigma "
                                  "uncertainty of a focal length or of the baseline exceeds "
                                  "this share of its value, or that of a principal point this "
                                  "share of the focal length"),
    "warn_sigma_pct": Setting("float", default=0.25, min=0.0001, unit="%",
                              help="a principal point or focal length whose one-sigma exceeds "
                                   "this share of the focal length is named as poorly "
                                   "determined, with the pose that would determine it"),
    "max_blur_px": Setting("float", default=6.0, min=0.5, unit="px",
                           help="checkerboard edges wider than this (10–90 % rise) mark the "
                                "pose blurred"),
    "window": Setting("float", default=0.45, min=0.1, max=1.0,
                      help="local-homography window half-size as a fraction of the corner "
                           "spacing in the image"),
    "poses": Setting("matrix", default=[], help="free poses of the board for camera and "
                     "projector: rows of [roll, tilt, pan (deg), centre x, y, z (mm)] in the "
                     "sample frame at stage angle 0"),
    "turntable_angles_deg": Setting("list[float]", default=[], unit="deg",
                                    help="stage angles at which the board on the stage is "
                                         "captured for the turntable axis"),
    "turntable_pose": Setting("list[float]", default=[0.0, -30.0, 0.0, 0.0, 0.0, 16.0],
                              length=6, help="board pose on the stage for the axis: [roll, "
                              "tilt, pan (deg), centre x, y, z (mm)]; z is the height of the "
                              "board centre above the plate (measure it on a real rig)"),
}
