"""Profile sections for trans-illumination capture (``[transillumination]``) and intensity
normalization on the scanned surface (``[normalize]``). See docs/transillumination.md."""

from __future__ import annotations

from dotshell.settings import Setting

TRANSILLUMINATION_SCHEMA: dict[str, Setting] = {
    "enabled": Setting("bool", default=False,
                       help="capture trans-illumination frames at every view of the scan "
                            "(needs a [light_source])"),
    "exposure_ms": Setting("float", default=50.0, min=0.001, unit="ms",
                           help="camera exposure for the trans-illumination, dark and "
                                "flat-field frames"),
    "targets_mm": Setting("matrix", default=[], unit="mm",
                          help="source positions: [lateral, height] pairs the light source is "
                               "aimed at (needs a targetable source); empty = one position, "
                               "wherever the source points"),
    "views": Setting("list[int]", default=[],
                     help="indices of the scan's views to trans-illuminate; empty = all"),
    "dark": Setting("bool", default=True,
                    help="also capture a frame with the source off at each view and subtract "
                         "it (ambient light, black level)"),
    "flat_field": Setting("str", default="capture",
                          help="'capture' (the rig shows the camera a uniform field once per "
                               "scan, if it can), 'none', or an image file (relative to the "
                               "profile) of a uniform field taken with the same camera"),
}

NORMALIZE_SCHEMA: dict[str, Setting] = {
    "after_scan": Setting("bool", default=True,
                          help="normalize at the end of a scan that captured "
                               "trans-illumination frames (needs [mesh] after_scan)"),
    "min_sin_beta": Setting("float", default=0.3, min=0.0, max=1.0,
                            help="nodes seen more grazing than this (sin β = cosine between "
                                 "normal and direction to the camera) are masked"),
    "compare": Setting("list[str]", default=["lambertian", "none"],
                       help="further normalizer backends reported side by side with "
                            "[normalizer]"),
    "saturation_fraction": Setting("float", default=0.98, min=0.5, max=1.0,
                                   help="pixels at or above this fraction of the camera's full "
                                        "scale count as saturated"),
    "max_normal_spread_deg": Setting("float", default=20.0, min=0.0, max=180.0, unit="deg",
                                     help="nodes whose surface turns more than this within "
                                          "their star (sharp edges, features smaller than the "
                                          "node spacing) are masked as crease"),
    "max_cloud_distance_mm": Setting("float", default=0.5, min=0.01, unit="mm",
                                     help="nodes farther than this from every scanned point "
                                          "(the closed bottom, filled holes) are masked as "
                                          "unscanned"),
    "min_pixels": Setting("float", default=2.0, min=0.0,
                          help="nodes covered by fewer camera pixels (hat-weighted) are masked "
                               "as unsampled"),
}
