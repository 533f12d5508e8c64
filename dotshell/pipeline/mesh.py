"""The mesh stage: a run's ``cloud.ply`` → closed ``surface.ply`` → tetrahedral
``volume.vtu`` (+ ``optodes.json``, previews, a ``mesh`` section in ``report.json``), and the
forward check on a run's volume mesh.

The surface and volume meshers are the profile's ``[surface_mesher]`` / ``[volume_mesher]``
backends (defaults ``open3d-poisson`` and ``tetgen``); ``[mesh]`` sets the node distance, the
plane the open bottom is closed at, the optical properties written per node and the optodes.
The primary node distance writes into the run directory itself (where the exporters look);
each of ``[mesh] also_node_distances_mm`` into ``meshes/<d>mm/``.
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from dotshell.errors import RunError
from dotshell.events import EventBus, StepStarted
from dotshell.fem.meshes import MeshError, TetMesh, quality_report
from dotshell.geometry.calibration import RigCalibration
from dotshell.profile.mesh import MESH_SCHEMA
from dotshell.fem.meshfiles import (optodes_from_settings, read_optodes, read_volume, write_optodes,
                                write_surface, write_volume)
from dotshell.plugins import PluginManager
from dotshell.run.layout import RunLayout
from dotshell.run.ply import read_ply
from dotshell.profile.loader import Profile
from dotshell.profile.sections import MeshSettings
from dotshell.run.store import RunStore

DEFAULT_BACKENDS = {"surface_mesher": "open3d-poisson", "volume_mesher": "tetgen"}
#: Largest volume mesh made (nodes, estimated before meshing): at 1 mm a 30 mm phantom has
#: ~31 k; 5 M take tens of GB and hours, so a typo such as 0.001 mm is refused at once.
MAX_MESH_NODES = 5_000_000


def _mesher(profile: Profile, pm: PluginManager, role: str):
    section = profile.role(role) or {"backend": DEFAULT_BACKENDS[role], "settings": {}}
    return pm.create(role, section["backend"], section["settings"], None, profile.source)


def viewpoints_mm(store: RunStore, views: np.ndarray,
                  calib: RigCalibration | None = None) -> np.ndarray | None:
    """Camera centre (sample frame, mm) of the view each point came from, or None."""
    try:
        calib = calib or RigCalibration.load(store.path(RunLayout.CALIBRATION))
        angles = {v["index"]: v["angle_deg"] for v in store.manifest["views"]}
    except Exception:  # a cloud without its run's calibration: orient by the centroid
        return None
    centres = {i: calib.camera_to_sample(np.zeros((1, 3)), a)[0] for i, a in angles.items()}
    ids = views.astype(int)
    if not set(np.unique(ids)) <= set(centres):
        return None
    table = np.array([centres[i] for i in sorted(centres)])
    return table[np.searchsorted(sorted(centres), ids)]


def mesh_stage(store: RunStore, profile: Profile, pm: PluginManager, bus: EventBus,
               node_distance_mm: float | None = None,
               calib: RigCalibration | None = None) -> dict[str, Any]:
    """Mesh the run's cloud at the profile's node distance(s); returns the report section.
    ``calib``: the run's calibration when the caller has it loaded (else read from the run)."""
    cfg = profile.mesh
    primary = cfg.node_distance_mm if node_distance_mm is None else node_distance_mm
    if not (isinstance(primary, (int, float)) and math.isfinite(primary) and primary > 0):
        raise MeshError(f"node distance must be a positive number of mm, got {primary!r}; set "
                        "[mesh] node_distance_mm or pass --node-distance (e.g. 1.0).")
    smallest = MESH_SCHEMA["node_distance_mm"].min
    if node_distance_mm is not None and smallest is not None and node_distance_mm < smallest:
        raise MeshError(f"--node-distance {node_distance_mm:g} mm is below the smallest node "
                        f"distance [mesh] node_distance_mm allows ({smallest:g} mm); give a "
                        "larger one (e.g. 1.0).")
    points, scalars = read_ply(store.path(RunLayout.CLOUD))
    if len(points) == 0:
        raise MeshError(f"{store.path(RunLayout.CLOUD)} has no points; nothing to mesh.")
    for d in [primary, *cfg.also_node_distances_mm]:
        refuse_huge_mesh(points, d)
    views = viewpoints_mm(store, scalars["view"], calib) if "view" in scalars else None
    surface_mesher = _mesher(profile, pm, "surface_mesher")
    volume_mesher = _mesher(profile, pm, "volume_mesher")
    optodes = optodes_from_settings(cfg.optodes.as_table(), profile.source)
    bottom = cfg.bottom_z_mm if cfg.close_bottom else None
    out: dict[str, Any] = {"meshes": []}
    extras = [d for d in cfg.also_node_distances_mm if d != primary]
    for d in [primary, *extras]:
        target = store.root if d == primary else store.path(RunLayout.mesh_dir(d))
        bus.emit(StepStarted(step=f"mesh {d:g} mm"))
        entry = mesh_one(points, views, d, bottom, surface_mesher, volume_mesher, cfg, optodes,
                         target)
        entry["dir"] = "." if target == store.root else str(target.relative_to(store.root))
        _validate_volume(entry, profile)
        if cfg.previews:
            entry["previews"] = _previews(store, target, d, bus)
        out["meshes"].append(entry)
    return out


def estimated_nodes(points: np.ndarray, node_distance_mm: float) -> int:
    """Nodes of a volume mesh of the cloud at ``node_distance_mm``: its bounding box's volume
    over the node distance cubed (the order of tetgen's count; the test phantom's cloud at
    1 mm: 6,980)."""
    extent = np.ptp(points, axis=0) if len(points) else np.zeros(3)
    return int(np.prod(np.maximum(extent, node_distance_mm)) / node_distance_mm ** 3)


def refuse_huge_mesh(points: np.ndarray, node_distance_mm: float) -> None:
    """Refuse, before any work, a mesh above :data:`MAX_MESH_NODES` nodes, with the estimate."""
    n = estimated_nodes(points, node_distance_mm)
    if n > MAX_MESH_NODES:
        raise MeshError(f"a mesh at {node_distance_mm:g} mm would have about {n:,} nodes, more "
                        f"than the {MAX_MESH_NODES:,} dotshell makes (hours and tens of GB); give "
                        "a larger node distance ([mesh] node_distance_mm, also_node_distances_mm "
                        "or --node-distance).")


def mesh_one(points, views, node_distance_mm: float, bottom_z_mm: float | None, surface_mesher,
             volume_mesher, cfg: MeshSettings, optodes, target: Path) -> dict[str, Any]:
    """Surface + volume at one node distance, written into ``target``."""
    t0 = time.perf_counter()
    result = surface_mesher.surface(points, views, node_distance_mm, bottom_z_mm)
    t_surface = time.perf_counter() - t0
    t0 = time.perf_counter()
    volume = volume_mesher.volume(result.surface, node_distance_mm)
    t_volume = time.perf_counter() - t0
    n = len(volume.nodes)
    optics = cfg.optics
    volume.point_data = {
        "region": np.ones(n, np.int32),
        "mua_per_mm": np.full(n, optics.mua_per_mm),
        "musp_per_mm": np.full(n, optics.musp_per_mm),
        "refractive_index": np.full(n, optics.refractive_index),
    }
    target.mkdir(parents=True, exist_ok=True)
    write_surface(target / RunLayout.SURFACE, result.surface)
    write_volume(target / RunLayout.VOLUME, volume)
    if not optodes.empty:
        write_optodes(target / RunLayout.OPTODES, optodes)
    elif (target / RunLayout.OPTODES).exists():
        os.unlink(target / RunLayout.OPTODES)
    return {
        "node_distance_mm": node_distance_mm,
        "surface": {k: v for k, v in result.stats.items() if not k.startswith("seconds")},
        "volume": quality_report(volume, result.surface),
        "timings_s": {"surface": round(t_surface, 3), "volume": round(t_volume, 3),
                      **{k.replace("seconds_", "surface_"): v for k, v in result.stats.items()
                         if k.startswith("seconds")}},
    }


def _validate_volume(entry: dict[str, Any], profile: Profile) -> None:
    """Against a known cylinder standing on the plate: the solid from the bottom plane to the
    top (the region of interest dropped the lowest band; the surface closes it at the plate)."""
    v = profile.validation
    if v.shape != "cylinder" or not profile.mesh.close_bottom:
        return
    bottom = profile.mesh.bottom_z_mm
    true = math.pi * v.radius_mm ** 2 * (v.height_mm - bottom)
    got = entry["volume"]["volume_mm3"]
    entry["validation"] = {"true_volume_mm3": true, "volume_error_pct": 100 * (got - true) / true,
                           "section_mm": [bottom, v.height_mm]}


def _previews(store: RunStore, target: Path, node_distance_mm: float, bus: EventBus) -> dict:
    from dotshell.render.mesh_previews import render_mesh_previews

    try:
        files = render_mesh_previews(target, store.path(RunLayout.PREVIEWS),
                                     f"_{RunLayout.mesh_dir_name(node_distance_mm)}")
    except Exception as exc:  # rendering depends on the machine's OpenGL; degrade
        bus.warn(f"mesh previews skipped: 3-D rendering is not available here "
                 f"({type(exc).__name__}: {exc}). The meshes are written.")
        return {}
    return {k: str(Path(p).relative_to(store.root)) for k, p in files.items()}


def forward_stage(store: RunStore, source_mm: list[float] | None = None,
                  mesh_dir: str = ".") -> dict[str, Any]:
    """CW fluence for a point source on the volume mesh in ``mesh_dir`` of the run's
    products, written as ``forward.vtu`` (point data ``fluence``) beside it; returns figures
    for the report (``file`` relative to the run)."""
    from dotshell.fem.forward import move_inside, solve_cw
    from dotshell.fem.meshfiles import _atomic_meshio

    d = store.path(mesh_dir)
    mesh = read_volume(d / RunLayout.VOLUME)
    source = _default_source(mesh, d) if source_mm is None else np.asarray(source_mm, float)
    if not np.all(np.isfinite(source)) or source.shape != (3,):
        raise RunError(f"--source must be three finite numbers (x y z in mm), got {source_mm!r}.")
    if not _inside(mesh, source):  # a source on the skin: one 1/μs' inside, like NIRFAST
        musp = float(np.mean(mesh.point_data.get("musp_per_mm", np.array([1.0]))))
        source = move_inside(mesh, source, 1.0 / musp)
    t0 = time.perf_counter()
    res = solve_cw(mesh, source)
    seconds = time.perf_counter() - t0
    import meshio

    data = {**mesh.point_data, "fluence": res.fluence}
    _atomic_meshio(d / RunLayout.FORWARD, meshio.Mesh(mesh.nodes, [("tetra", mesh.tets)],
                                                  point_data=data), "vtu")
    b = mesh.boundary_nodes
    fb = res.fluence[b]
    out = {"mesh_dir": mesh_dir, "source_mm": res.source_mm.tolist(), "nodes": len(mesh.nodes),
           "elements": len(mesh.tets), "robin_A": res.A, "solve_s": round(seconds, 3),
           "boundary_fluence_per_mm2": {"min": float(fb.min()), "median": float(np.median(fb)),
                                        "max": float(fb.max())},
           "negative_nodes": int((res.fluence < 0).sum()),
           "file": str(Path(mesh_dir) / RunLayout.FORWARD)}
    optodes = read_optodes(d / RunLayout.OPTODES)
    if len(optodes.detectors_mm):
        from scipy.spatial import cKDTree

        _, idx = cKDTree(mesh.nodes[b]).query(optodes.detectors_mm)
        out["detector_fluence_per_mm2"] = fb[idx].tolist()
    return out


def _inside(mesh: TetMesh, point: np.ndarray) -> bool:
    from dotshell.fem.meshes import element_containing

    try:
        element_containing(mesh, point)
    except MeshError:
        return False
    return True


def _default_source(mesh: TetMesh, d: Path) -> np.ndarray:
    """The first optode source, else the centroid of the mesh volume."""
    optodes = read_optodes(d / RunLayout.OPTODES)
    if len(optodes.sources_mm):
        return optodes.sources_mm[0]
    from dotshell.fem.meshes import signed_volumes_mm3

    vol = signed_volumes_mm3(mesh.nodes, mesh.tets)
    return (mesh.nodes[mesh.tets].mean(axis=1) * vol[:, None]).sum(axis=0) / vol.sum()
