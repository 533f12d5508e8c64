"""The profile's ``[mesh]`` section (documented in ``docs/profiles.md``); see
:mod:`dotshell.pipeline.mesh`."""

from __future__ import annotations

from dotshell.settings import Setting

MESH_SCHEMA: dict[str, Setting] = {
    "after_scan": Setting("bool", default=False, help="run the mesh stage (surface, volume) at "
                          "the end of `dotshell scan` / `dotshell reconstruct`, before exports"),
    "node_distance_mm": Setting("float", default=1.0, min=0.05, unit="mm",
                                help="target distance between mesh nodes"),
    "also_node_distances_mm": Setting("list[float]", default=[], min=0.05, unit="mm",
                                      help="further node distances, each meshed into "
                                           "meshes/<d>mm/ (no exports)"),
    "close_bottom": Setting("bool", default=True, help="close the open bottom of the cloud at "
                            "the plate plane bottom_z_mm (the sample stood there)"),
    "bottom_z_mm": Setting("float", default=0.0, unit="mm",
                           help="height of the plane the bottom is closed at (plate = 0)"),
    "previews": Setting("bool", default=True, help="render surface and volume PNG previews"),
    "optics": Setting("table", default={}, help="optical properties written for every node",
                      schema={
        "mua_per_mm": Setting("float", default=0.01, min=0.0, unit="1/mm",
                              help="absorption coefficient μa"),
        "musp_per_mm": Setting("float", default=1.0, min=1e-6, unit="1/mm",
                               help="reduced scattering coefficient μs'"),
        "refractive_index": Setting("float", default=1.33, min=1.0, help="refractive index n"),
    }),
    "optodes": Setting("table", default={}, help="sources and detectors for NIRFAST/TOAST "
                       "files and `dotshell forward`", schema={
        "sources_mm": Setting("matrix", default=[], unit="mm",
                              help="source positions [[x, y, z], ...], sample frame"),
        "detectors_mm": Setting("matrix", default=[], unit="mm",
                                help="detector positions [[x, y, z], ...], sample frame"),
        "links": Setting("matrix", default=[], help="[[source, detector], ...] 0-based; "
                         "empty = every source with every detector"),
    }),
}
