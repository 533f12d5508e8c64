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
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dotshell.errors import RunError
from dotshell.events import EventBus, StepStarted
from dotshell.fem.meshes import (MeshError, SurfaceResult, TetMesh, TriangleSurface,
                                 boundary_faces_by_sorting, quality_report)
from dotshell.geometry.calibration import RigCalibration
from dotshell.profile.mesh import MESH_SCHEMA
from dotshell.fem.meshfiles import (optodes_from_settings, read_optodes, read_volume, write_optodes,
                                write_surface, write_volume)
from dotshell.plugins import PluginManager
from dotshell.run.layout import RunLayout
from dotshell.pipeline.mesh_process import discard_early, picklable, run_in_child
from dotshell.run.ply import map_ply
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


class ViewpointsPerPoint:
    """The camera centre (sample frame, mm) that saw each point of a cloud, made a slice at a
    time: ``vp[a:b]`` is the (b − a, 3) float64 array of the centres of points a..b-1 (the whole
    (N, 3) array of an 8.3 M-point cloud took 200 MB, and the surface mesher reads it a chunk
    at a time)."""

    def __init__(self, view_ids: np.ndarray, view_indices: np.ndarray, centres_mm: np.ndarray):
        self._ids = view_ids
        self._keys = view_indices
        self._centres = centres_mm
        # the centres by view index when the indices are small: np.take of a chunk's rows
        # (250 k: 1.0 ms) instead of searchsorted and fancy indexing (3.7 ms), the same values
        self._table: np.ndarray | None = None
        if len(view_indices) and view_indices.min() >= 0 and view_indices.max() < 1 << 20:
            self._table = np.zeros((int(view_indices.max()) + 1, 3), centres_mm.dtype)
            self._table[view_indices] = centres_mm

    def __len__(self) -> int:
        return len(self._ids)

    def __getitem__(self, index: slice) -> np.ndarray:
        ids = np.asarray(self._ids[index]).astype(int)
        if self._table is not None:
            return np.take(self._table, ids, axis=0)
        return self._centres[np.searchsorted(self._keys, ids)]


@dataclass
class ViewCentres:
    """The camera centre (sample frame, mm) of each view of a run, by view index."""

    indices: np.ndarray
    centres_mm: np.ndarray

    @classmethod
    def of_run(cls, store: RunStore, calib: RigCalibration | None = None) -> ViewCentres | None:
        """From the run's calibration (``calib``, else read from the run) and stage angles;
        None without them."""
        try:
            calib = calib or RigCalibration.load(store.path(RunLayout.CALIBRATION))
            angles = {v["index"]: v["angle_deg"] for v in store.manifest["views"]}
        except Exception:  # a cloud without its run's calibration: orient by the centroid
            return None
        keys = sorted(angles)
        return cls(np.array(keys, int), np.array(
            [calib.camera_to_sample(np.zeros((1, 3)), angles[i])[0] for i in keys]))

    def per_point(self, views: np.ndarray) -> ViewpointsPerPoint | None:
        """The centre of the view each point came from (``views``: each point's view index);
        None when a point names a view the run does not list."""
        if not self.lists_every(views):
            return None
        return ViewpointsPerPoint(views, self.indices, self.centres_mm)

    def lists_every(self, views: np.ndarray, chunk: int = 1 << 20) -> bool:
        """Whether each value of ``views`` is one of :attr:`indices` (``np.isin(views,
        indices).all()``): ``chunk`` values at a time through a table of the listed indices
        when they are small non-negative integers (the sort-based ``np.isin`` of the demo's
        5.5 M float32 view numbers took 0.075 s of the mesh process's CPU)."""
        keys = np.asarray(self.indices)
        if len(keys) == 0 or keys.min() < 0 or keys.max() >= 1 << 20:
            return bool(np.isin(views, keys).all())
        listed = np.zeros(int(keys.max()) + 1, bool)
        listed[keys] = True
        for s in range(0, len(views), chunk):
            part = np.asarray(views[s:s + chunk])
            if not (part.min() >= 0 and part.max() < len(listed)):  # NaN fails here too
                return False
            ids = part.astype(np.intp)
            if not ((ids == part).all() and listed[ids].all()):
                return False
        return True


@dataclass
class MeshJob:
    """What the mesh process needs to mesh a run's cloud (plain data and the meshers: it is
    pickled into the process, :mod:`dotshell.pipeline.mesh_process`); ``optodes`` are written
    beside the meshes by the command's process."""

    cloud: Path
    view_centres: ViewCentres | None
    node_distances_mm: list[float]
    bottom_z_mm: float | None
    surface_mesher: Any
    volume_mesher: Any
    cfg: MeshSettings
    optodes: Any


def mesh_cloud(job: MeshJob, node_distance_mm: float) -> tuple[TriangleSurface, TetMesh,
                                                                 dict[str, Any]]:
    """Read the cloud (memory-mapped, no copies), refuse a huge mesh at any of the job's node
    distances, make the surface at ``node_distance_mm``, let the cloud go (its mapped pages
    were the largest part of the process's peak, with TetGen's and the quality figures' memory
    on top), then the volume; the surface, the volume (with its per-node optics) and the report
    entry. Runs in the mesh process; writes nothing (the run's files are written by the
    command's process, where a full disk is reported as everywhere else)."""
    points, scalars = map_ply(job.cloud)
    if len(points) == 0:
        raise MeshError(f"{job.cloud} has no points; nothing to mesh.")
    for d in job.node_distances_mm:
        refuse_huge_mesh(points, d)
    views = None
    if job.view_centres is not None and "view" in scalars:
        views = job.view_centres.per_point(scalars["view"])
    t0 = time.perf_counter()
    result = job.surface_mesher.surface(points, views, node_distance_mm, job.bottom_z_mm)
    t_surface = time.perf_counter() - t0
    del points, scalars, views
    return mesh_volume(result, t_surface, node_distance_mm, job.volume_mesher, job.cfg)



def mesh_stage(store: RunStore, profile: Profile, pm: PluginManager, bus: EventBus,
               node_distance_mm: float | None = None,
               calib: RigCalibration | None = None) -> dict[str, Any]:
    """Mesh the run's cloud at the profile's node distance(s); returns the report section.
    ``calib``: the run's calibration when the caller has it loaded (else read from the run).

    Each node distance is meshed in a process of its own (:func:`run_in_child`), unless a
    plugin's mesher cannot be handed to one (it does not pickle): then in this process."""
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
    job = mesh_job(store, profile, pm, primary, calib)
    in_child = picklable(job)
    if not in_child:
        discard_early()  # a mesh process started for the command gets no job
        bus.info("meshing in this process: a mesher of the profile cannot be handed to a "
                 "process of its own (it does not pickle)")
    out: dict[str, Any] = {"meshes": []}
    for d in job.node_distances_mm:
        target = store.root if d == primary else store.path(RunLayout.mesh_dir(d))
        bus.emit(StepStarted(step=f"mesh {d:g} mm"))
        surface, volume, entry = (run_in_child(mesh_cloud, job, d) if in_child
                                  else mesh_cloud(job, d))
        # the files written in a thread while the previews are drawn from the meshes in hand:
        # zlib releases the GIL, and compressing volume.vtu was 0.14 s of the demo's 0.3 s
        # after the mesh process
        with ThreadPoolExecutor(1) as writer:
            written = writer.submit(write_meshes, target, surface, volume, job.optodes)
            entry["dir"] = "." if target == store.root else str(target.relative_to(store.root))
            _validate_volume(entry, profile)
            if cfg.previews:
                entry["previews"] = _previews(store, target, d, bus, surface, volume)
            written.result()
        del surface, volume
        out["meshes"].append(entry)
    return out


def mesh_job(store: RunStore, profile: Profile, pm: PluginManager, primary_mm: float,
             calib: RigCalibration | None = None) -> MeshJob:
    """The job of meshing the run's cloud at ``primary_mm`` and the profile's
    ``[mesh] also_node_distances_mm``, with the profile's meshers."""
    cfg = profile.mesh
    extras = [d for d in cfg.also_node_distances_mm if d != primary_mm]
    return MeshJob(store.path(RunLayout.CLOUD), ViewCentres.of_run(store, calib),
                   [primary_mm, *extras], cfg.bottom_z_mm if cfg.close_bottom else None,
                   _mesher(profile, pm, "surface_mesher"), _mesher(profile, pm, "volume_mesher"),
                   cfg, optodes_from_settings(cfg.optodes.as_table(), profile.source))


def estimated_nodes(points: np.ndarray, node_distance_mm: float) -> int:
    """Nodes of a volume mesh of the cloud at ``node_distance_mm``: its bounding box's volume
    over the node distance cubed (the order of tetgen's count; the test phantom's cloud at
    1 mm: 6,980)."""
    # column by column: np.ptp(axis=0) of the mapped (N, 3) cloud, whose rows are 16 bytes
    # apart, took 0.3-0.6 s for 5.5 M points, a column 7 ms (the same values)
    extent = (np.array([np.ptp(points[:, k]) for k in range(3)]) if len(points)
              else np.zeros(3))
    return int(np.prod(np.maximum(extent, node_distance_mm)) / node_distance_mm ** 3)


def refuse_huge_mesh(points: np.ndarray, node_distance_mm: float) -> None:
    """Refuse, before any work, a mesh above :data:`MAX_MESH_NODES` nodes, with the estimate."""
    n = estimated_nodes(points, node_distance_mm)
    if n > MAX_MESH_NODES:
        raise MeshError(f"a mesh at {node_distance_mm:g} mm would have about {n:,} nodes, more "
                        f"than the {MAX_MESH_NODES:,} dotshell makes (hours and tens of GB); give "
                        "a larger node distance ([mesh] node_distance_mm, also_node_distances_mm "
                        "or --node-distance).")


def mesh_volume(result: SurfaceResult, t_surface: float, node_distance_mm: float, volume_mesher,
                cfg: MeshSettings) -> tuple[TriangleSurface, TetMesh, dict[str, Any]]:
    """The volume of a surface mesher's ``result`` (made in ``t_surface`` s) at one node
    distance, with ``[mesh.optics]`` per node; the surface, the volume and the report entry."""
    t0 = time.perf_counter()
    volume = volume_mesher.volume(result.surface, node_distance_mm)
    t_volume = time.perf_counter() - t0
    # the boundary (quality figures, volume.vtu) sorted with numpy: this process would
    # otherwise start numba for it alone (~0.9 s of CPU)
    volume.boundary_faces = boundary_faces_by_sorting(volume.tets)
    n = len(volume.nodes)
    optics = cfg.optics
    volume.point_data = {
        "region": np.ones(n, np.int32),
        "mua_per_mm": np.full(n, optics.mua_per_mm),
        "musp_per_mm": np.full(n, optics.musp_per_mm),
        "refractive_index": np.full(n, optics.refractive_index),
    }
    return result.surface, volume, {
        "node_distance_mm": node_distance_mm,
        "surface": {k: v for k, v in result.stats.items() if not k.startswith("seconds")},
        "volume": quality_report(volume, result.surface),
        "timings_s": {"surface": round(t_surface, 3), "volume": round(t_volume, 3),
                      **{k.replace("seconds_", "surface_"): v for k, v in result.stats.items()
                         if k.startswith("seconds")}},
    }


def write_meshes(target: Path, surface: TriangleSurface, volume: TetMesh, optodes) -> None:
    """``surface.ply``, ``volume.vtu`` and ``optodes.json`` (or none) into ``target``."""
    target.mkdir(parents=True, exist_ok=True)
    write_surface(target / RunLayout.SURFACE, surface)
    write_volume(target / RunLayout.VOLUME, volume)
    if not optodes.empty:
        write_optodes(target / RunLayout.OPTODES, optodes)
    elif (target / RunLayout.OPTODES).exists():
        os.unlink(target / RunLayout.OPTODES)


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


def _previews(store: RunStore, target: Path, node_distance_mm: float, bus: EventBus,
              surface: TriangleSurface, volume: TetMesh) -> dict:
    from dotshell.render.mesh_previews import render_mesh_previews

    try:
        files = render_mesh_previews(target, store.path(RunLayout.PREVIEWS),
                                     f"_{RunLayout.mesh_dir_name(node_distance_mm)}",
                                     surface, volume)
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
