"""The CW forward solve of ``dotshell forward`` on the agar cylinder's volume mesh, against a
sparse LU of the same system (issue 16: "``dotshell forward`` on the agar mesh ≤ 1 s").

The mesh is the simulator's true-shape FEM of the agar cylinder of
``profiles/sim-agar-cylinder.toml`` (its scene's radius and height; TetGen with the quality
bounds of :func:`dotshell_sim.transillum.tetrahedralize`, at the profile's ``[mesh]``
node_distance_mm, 1.0 mm: ~31 k nodes; 2.0 mm with ``--quick``), with the profile's
``[mesh.optics]`` per node, written once as a ``volume.vtu`` the way ``dotshell mesh`` writes it.
It needs no scan: a scanned agar mesh at 1.0 mm has about the same size (31 187 nodes against
31 488) and is minutes of simulation away, while this one is built in seconds and is the same
on every run.

Each repeat, interleaved (the order alternates), from a freshly read ``volume.vtu`` and the
source at the mesh's centroid (``dotshell forward``'s default without optodes):

* ``dotshell``: :func:`dotshell.fem.forward.solve_cw` — assembly, boundary faces, source element,
  Jacobi-preconditioned CG (what ``dotshell forward`` times as ``solve_s``);
* the same steps one by one (boundary faces, source element, assembly, CG), to show where
  ``solve_cw``'s time goes;
* ``splu``: the same assembly (:func:`dotshell.fem.forward.system_matrix`) and source vector, then
  ``scipy.sparse.linalg.splu`` with COLAMD ordering and its solve (``dotshell forward``'s solver
  before issue 16). At 1.0 mm it takes tens of seconds, so it runs ``lu_repeats`` times only.

Wall and CPU seconds (``time.process_time``: every thread of the process) are reported as min
and median of the repeats, with the agreement ``max |φ_CG − φ_LU| / max φ_LU``.
"""

from __future__ import annotations

import os
import time
import tomllib
from pathlib import Path
from typing import Any, Callable

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from bench_profile import ROOT
from frame_io import min_median
from dotshell.fem.meshes import TetMesh, element_containing
from dotshell.fem.forward import jacobi_cg, robin_A, solve_cw, system_matrix
from dotshell.fem.meshfiles import read_volume, write_volume
from dotshell.pipeline.mesh import _default_source

AGAR_PROFILE = ROOT / "profiles" / "sim-agar-cylinder.toml"
#: node spacing of the ``--quick`` mesh, mm (the full mesh uses the profile's node_distance_mm)
QUICK_SPACING_MM = 2.0
#: issue 16: ``dotshell forward`` on the agar mesh, seconds
FORWARD_BOUND_S = 1.0


def agar_volume(spacing_mm: float | None) -> tuple[TetMesh, float]:
    """The agar cylinder's tetrahedral mesh (sample frame, mm) with its ``[mesh.optics]`` per
    node, and the node spacing used (the profile's node_distance_mm when ``None``)."""
    from dotshell_sim.scene import Cylinder
    from dotshell_sim.transillum import tetrahedralize, true_surface

    raw = tomllib.loads(AGAR_PROFILE.read_text(encoding="utf-8"))
    scene, mesh_cfg = raw["stage"]["settings"]["scene"], raw["mesh"]
    spacing = float(spacing_mm or mesh_cfg["node_distance_mm"])
    shape = Cylinder(float(scene["radius_mm"]), float(scene["height_mm"]))
    mesh = tetrahedralize(true_surface(shape, spacing), spacing)
    n = len(mesh.nodes)
    mesh.point_data = {"region": np.ones(n, np.int32),
                       **{k: np.full(n, float(v)) for k, v in mesh_cfg["optics"].items()}}
    return mesh, spacing


def _timed(fn: Callable[[], Any]) -> tuple[Any, float, float]:
    """``fn()``, its wall and CPU seconds."""
    w0, c0 = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - w0, time.process_time() - c0


def assemble(mesh: TetMesh, source_mm: np.ndarray
             ) -> tuple[sp.csr_matrix, np.ndarray, dict[str, float]]:
    """The system and source vector ``solve_cw`` builds, step by step as it does, with each
    step's wall seconds: boundary faces, source element, assembly."""
    pd = mesh.point_data
    mua, musp = pd["mua_per_mm"], pd["musp_per_mm"]
    _, faces_s, _ = _timed(lambda: mesh.boundary_faces)
    A = robin_A(float(np.mean(pd["refractive_index"][mesh.boundary_nodes])))
    (el, w), element_s, _ = _timed(lambda: element_containing(mesh, source_mm))
    q = np.zeros(len(mesh.nodes))
    q[mesh.tets[el]] = w
    kappa = 1.0 / (3.0 * (mua + musp))
    matrix, assembly_s, _ = _timed(lambda: system_matrix(mesh, mua, kappa, A))
    return matrix, q, {"boundary_faces": faces_s, "source_element": element_s,
                       "assembly": assembly_s}


def solve_parts(mesh: TetMesh, source_mm: np.ndarray) -> dict[str, float]:
    """Wall seconds of ``solve_cw``'s steps taken one by one: those of :func:`assemble`, and
    the Jacobi CG."""
    matrix, q, seconds = assemble(mesh, source_mm)
    _, seconds["cg"], _ = _timed(lambda: jacobi_cg(matrix, q))
    return seconds


def solve_lu(mesh: TetMesh, source_mm: np.ndarray) -> tuple[np.ndarray, float, float]:
    """φ for a unit source by ``splu`` (COLAMD) of the system ``solve_cw`` assembles; with the
    wall and CPU seconds of the factorization and solve alone."""
    matrix, q, _ = assemble(mesh, source_mm)
    return _timed(lambda: sla.splu(matrix.tocsc(), permc_spec="COLAMD").solve(q))


def measure(work: Path, quick: bool, repeats: int, lu_repeats: int) -> dict[str, Any]:
    """Seconds (wall and CPU, min and median) of the CG solve and the LU peer, interleaved."""
    (mesh, spacing), build_s, _ = _timed(lambda: agar_volume(QUICK_SPACING_MM if quick
                                                             else None))
    path = work / "forward-agar" / "volume.vtu"
    path.parent.mkdir(parents=True, exist_ok=True)
    write_volume(path, mesh)
    source = _default_source(mesh, path.parent)  # no optodes.json: the centroid
    runs: dict[str, list[float]] = {k: [] for k in ("read_wall", "cg_wall", "cg_cpu", "lu_wall",
                                                    "lu_cpu", "lu_factor_wall",
                                                    "lu_factor_cpu")}
    cg = lu = None
    for r in range(max(repeats, lu_repeats)):
        sides = ["cg", "parts"] * (r < repeats) + ["lu"] * (r < lu_repeats)
        for side in (sides if r % 2 == 0 else sides[::-1]):
            fresh, read_s, _ = _timed(lambda: read_volume(path))
            runs["read_wall"].append(read_s)
            if side == "parts":
                for key, value in solve_parts(fresh, source).items():
                    runs.setdefault(f"part_{key}_wall", []).append(value)
            elif side == "cg":
                res, wall, cpu = _timed(lambda: solve_cw(fresh, source))
                cg = res.fluence
                runs["cg_wall"].append(wall)
                runs["cg_cpu"].append(cpu)
            else:
                (lu, f_wall, f_cpu), wall, cpu = _timed(lambda: solve_lu(fresh, source))
                for key, value in (("lu_wall", wall), ("lu_cpu", cpu),
                                   ("lu_factor_wall", f_wall), ("lu_factor_cpu", f_cpu)):
                    runs[key].append(value)
    out: dict[str, Any] = {k: min_median(v) for k, v in runs.items()}
    out.update(nodes=len(mesh.nodes), elements=len(mesh.tets), spacing_mm=spacing,
               mesh_build_s=build_s, source_mm=np.asarray(source).tolist(), repeats=repeats,
               lu_repeats=lu_repeats, bound_s=FORWARD_BOUND_S,
               max_rel_diff=float(np.abs(cg - lu).max() / np.abs(lu).max()),
               loadavg=list(os.getloadavg()))
    return out


def print_forward(d: dict[str, Any]) -> None:
    """The section's table: CG and LU side by side, the ratio and the issue's bound."""
    print(f"\n== 8. forward solve on the agar cylinder mesh ({d['nodes']} nodes, "
          f"{d['elements']} tetrahedra, {d['spacing_mm']:g} mm; built in "
          f"{d['mesh_build_s']:.1f} s; min / median, s; CG x{d['repeats']}, "
          f"LU x{d['lu_repeats']}, interleaved) ==")
    print(f"  {'per solve of a freshly read mesh':44s} {'wall':>17s} {'CPU':>17s}")

    def row(label: str, wall: dict[str, float], cpu: dict[str, float] | None) -> None:
        c = f"{cpu['min']:7.3f} / {cpu['median']:7.3f}" if cpu else ""
        print(f"  {label:44s} {wall['min']:7.3f} / {wall['median']:7.3f} {c:>17s}")

    row("read volume.vtu (not in solve_s)", d["read_wall"], None)
    row("dotshell: solve_cw (Jacobi CG)", d["cg_wall"], d["cg_cpu"])
    for part in ("boundary_faces", "source_element", "assembly", "cg"):
        row(f"  step by step: {part.replace('_', ' ')}", d[f"part_{part}_wall"], None)
    row("splu COLAMD: assembly + factor + solve", d["lu_wall"], d["lu_cpu"])
    row("  of which factor + solve", d["lu_factor_wall"], d["lu_factor_cpu"])
    ratio = d["lu_wall"]["median"] / d["cg_wall"]["median"]
    cpu_ratio = d["lu_cpu"]["median"] / d["cg_cpu"]["median"]
    med = d["cg_wall"]["median"]
    print(f"  splu / CG: {ratio:.0f}x wall, {cpu_ratio:.0f}x CPU (medians); "
          f"max |φ_CG − φ_LU| / max φ = {d['max_rel_diff']:.1e}")
    print(f"  solve_cw median {med:.2f} s wall, {d['cg_cpu']['median']:.2f} s CPU: "
          f"{'within' if med <= d['bound_s'] else 'ABOVE'} issue 16's {d['bound_s']:g} s "
          f"(load average {d['loadavg'][0]:.1f})")


def main() -> None:
    """This section alone: ``python benchmarks/forward_bench.py [--quick] [--repeats N]``."""
    import argparse
    import tempfile

    from dotshell.runtime.process import configure_process

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help=f"{QUICK_SPACING_MM} mm mesh")
    ap.add_argument("--repeats", type=int, default=5, help="repeats of the CG solve")
    ap.add_argument("--lu-repeats", type=int, default=2, help="repeats of the LU peer")
    args = ap.parse_args()
    configure_process()  # BLAS on one thread, as the dotshell command runs
    with tempfile.TemporaryDirectory(prefix="dotshell-forward-") as tmp:
        print_forward(measure(Path(tmp), args.quick, args.repeats, args.lu_repeats))


if __name__ == "__main__":
    main()
