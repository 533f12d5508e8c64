"""Calibration of a rig from captured images of a planar target: camera intrinsics, projector
intrinsics and camera–projector pose (gray code on the target, local homographies), and the
turntable axis. ``schema`` holds the profile keys, ``board`` the target and its detection,
``solve`` the pure solvers, ``procedure`` the guided capture and the whole solve."""
