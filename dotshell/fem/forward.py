"""Continuous-wave diffusion forward model on a tetrahedral mesh (linear finite elements, as in
NIRFAST), and the analytic solution it is verified against.

The photon fluence φ (1/mm² per unit source power) solves

    −∇·(κ ∇φ) + μa φ = q   in the volume,   κ = 1 / (3 (μa + μs'))   [mm]
    φ + 2 A κ ∂φ/∂n = 0     on the boundary (Robin / extrapolated boundary)

with A from Fresnel reflection at the tissue–air boundary (refractive index n inside, 1
outside), the formula NIRFAST uses ("robin"):
``A = (2/(1 − R0) − 1 + |cos θc|³) / (1 − |cos θc|²)``, ``R0 = ((n − 1)/(n + 1))²``,
``θc = asin(1/n)``. The weak form gives the sparse system
``(K + M + B) φ = q``: stiffness ``∫κ ∇vi·∇vj``, mass ``∫μa vi vj``, boundary
``(1/2A) ∮ vi vj``, and a point source ``q = δ(x − x0)`` spread over the four nodes of its
element by barycentric weights. Units: mm, 1/mm.

The system matrix is symmetric positive definite; :func:`jacobi_cg` solves it by conjugate
gradients with a Jacobi (diagonal) preconditioner. On the agar cylinder's 31 k-node mesh (178 k
tetrahedra) the CG takes 0.13-0.2 s where a sparse LU (``splu``, COLAMD ordering) takes 20-30 s,
and agrees with the LU solution to ~2e-11 of the peak fluence. :func:`system_matrix` adds the
element matrices straight into the mesh's CSR pattern
(:attr:`~dotshell.fem.meshes.TetMesh.matrix_pattern`, built once per mesh; the loops are compiled, in
:mod:`dotshell.fem.kernels`): boundary faces and assembly of a freshly read mesh take
0.17-0.26 s, against ~0.7 s of CPU with numpy element matrices, ``np.unique`` boundary faces
and a COO → CSR conversion before, so :func:`solve_cw` takes 0.3-0.5 s (docs/performance.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from dotshell.fem.meshes import MeshError, TetMesh, element_containing, unique_values


def robin_A(n: float) -> float:
    """Boundary attenuation factor A for refractive index ``n`` against air (NIRFAST 'robin')."""
    if n < 1.0:
        raise MeshError(f"refractive index must be ≥ 1 (the outside is air), got {n}.")
    r0 = ((n - 1.0) / (n + 1.0)) ** 2
    cos_c = abs(math.cos(math.asin(1.0 / n)))
    if cos_c == 0.0:  # n = 1: no reflection, A = 1
        return 1.0
    return (2.0 / (1.0 - r0) - 1.0 + cos_c ** 3) / (1.0 - cos_c ** 2)


@dataclass
class ForwardResult:
    """Fluence per node (1/mm² per unit power) and what produced it."""

    fluence: np.ndarray
    source_mm: np.ndarray
    A: float
    element: int


def _per_node(value, n: int, name: str) -> np.ndarray:
    v = np.broadcast_to(np.asarray(value, float), (n,)).copy()
    if not np.isfinite(v).all():
        raise MeshError(f"{name} has non-finite values.")
    return v


def boundary_blocks(nodes: np.ndarray, faces: np.ndarray, A: float) -> np.ndarray:
    """(F, 3, 3) Robin boundary term ``(1/2A) ∮ vi vj`` of each face: area (mm²) / 12 / 2A ×
    (1 + δij)."""
    v = nodes[faces]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    return (area / 12.0 / (2.0 * A))[:, None, None] * (np.ones((3, 3)) + np.eye(3))


def system_matrix(mesh: TetMesh, mua: np.ndarray, kappa: np.ndarray, A: float) -> sp.csr_matrix:
    """(K + M + B) for per-node μa (1/mm) and κ (mm), element values = node means, assembled
    into the mesh's :attr:`~dotshell.fem.meshes.TetMesh.matrix_pattern`.

    Raises:
        MeshError: an element is inverted or flat.
    """
    from dotshell.fem.kernels import add_diffusion_elements  # numba: imported at first use

    pattern = mesh.matrix_pattern
    data = np.zeros(pattern.nnz)
    bad = add_diffusion_elements(data, pattern.tet_slots, mesh.nodes, mesh.tets,
                                 np.asarray(kappa, float), np.asarray(mua, float))
    if bad:
        raise MeshError(f"{bad} elements are inverted or flat; the FEM needs positively "
                        "oriented tetrahedra (re-run `dotshell mesh`).")
    face_blocks = boundary_blocks(mesh.nodes, mesh.boundary_faces, A)
    np.add.at(data, pattern.face_slots.ravel(), face_blocks.ravel())
    return pattern.matrix(data)


def solve_cw(mesh: TetMesh, source_mm, mua_per_mm=None, musp_per_mm=None,
             refractive_index: float | None = None) -> ForwardResult:
    """Fluence for a unit point source at ``source_mm`` (must lie inside the mesh). Optical
    properties default to the mesh's per-node ``point_data``; the boundary uses one refractive
    index (the mean of the boundary nodes' when not given)."""
    n = len(mesh.nodes)
    pd = mesh.point_data
    mua = _per_node(pd.get("mua_per_mm") if mua_per_mm is None else mua_per_mm, n, "μa")
    musp = _per_node(pd.get("musp_per_mm") if musp_per_mm is None else musp_per_mm, n, "μs'")
    if (mua < 0).any() or (musp <= 0).any():
        raise MeshError("optical properties must have μa ≥ 0 and μs' > 0 (1/mm).")
    if refractive_index is None:
        ri = pd.get("refractive_index")
        refractive_index = float(np.mean(ri[mesh.boundary_nodes])) if ri is not None else 1.33
    A = robin_A(refractive_index)
    src = np.asarray(source_mm, float).reshape(3)
    el, w = element_containing(mesh, src)
    q = np.zeros(n)
    q[mesh.tets[el]] = w
    kappa = 1.0 / (3.0 * (mua + musp))
    phi = jacobi_cg(system_matrix(mesh, mua, kappa, A), q)
    return ForwardResult(phi, src, A, el)


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    # einsum, not BLAS: OpenBLAS's threaded ddot is ~30x slower once open3d's threads ran
    return float(np.einsum("i,i->", a, b))


def jacobi_cg(matrix: sp.csr_matrix, rhs: np.ndarray, rtol: float = 1e-10) -> np.ndarray:
    """Solve a symmetric positive definite system by conjugate gradients with a Jacobi
    (diagonal) preconditioner, to ``|r| ≤ rtol · |rhs|``.

    Raises:
        MeshError: no convergence (the matrix is not positive definite: bad optical
            properties or a broken mesh).
    """
    inv_diag = 1.0 / matrix.diagonal()
    x = np.zeros_like(rhs)
    r = rhs.copy()
    z = inv_diag * r
    p = z.copy()
    rz = _dot(r, z)
    stop = (rtol ** 2) * _dot(rhs, rhs)
    for _ in range(20 * len(rhs)):
        if _dot(r, r) <= stop:
            return x
        ap = matrix @ p
        alpha = rz / _dot(p, ap)
        x += alpha * p
        r -= alpha * ap
        z = inv_diag * r
        rz_new = _dot(r, z)
        p = z + (rz_new / rz) * p
        rz = rz_new
    raise MeshError(f"the diffusion solve did not converge in {20 * len(rhs)} iterations; "
                    "check the optical properties (μa ≥ 0, μs' > 0 in 1/mm) and the mesh "
                    "(re-run `dotshell mesh`).")


def sphere_point_source_fluence(r_mm: np.ndarray, radius_mm: float, mua_per_mm: float,
                                musp_per_mm: float, refractive_index: float) -> np.ndarray:
    """Exact fluence at distance ``r_mm`` from a unit point source at the centre of a
    homogeneous sphere with the same Robin boundary condition: the infinite-medium Green's
    function ``e^(−kr)/(4πκr)`` plus the regular solution ``C sinh(kr)/r`` fixing
    ``φ + 2Aκ φ' = 0`` at ``r = R`` (k = √(μa/κ))."""
    kappa = 1.0 / (3.0 * (mua_per_mm + musp_per_mm))
    k = math.sqrt(mua_per_mm / kappa)
    A = robin_A(refractive_index)
    R = radius_mm
    G = math.exp(-k * R) / (4 * math.pi * kappa * R)
    dG = -math.exp(-k * R) * (k * R + 1) / (4 * math.pi * kappa * R * R)
    H = math.sinh(k * R) / R
    dH = (k * R * math.cosh(k * R) - math.sinh(k * R)) / (R * R)
    C = -(G + 2 * A * kappa * dG) / (H + 2 * A * kappa * dH)
    r = np.asarray(r_mm, float)
    return np.exp(-k * r) / (4 * math.pi * kappa * r) + C * np.sinh(k * r) / r


def move_inside(mesh: TetMesh, point_mm, depth_mm: float) -> np.ndarray:
    """The point ``depth_mm`` inside the surface below the boundary node nearest to
    ``point_mm``, along the inward area-weighted normal there — where NIRFAST puts a
    (non-fixed) source: one transport mean free path, 1/μs', under the skin."""
    faces = mesh.boundary_faces
    v = mesh.nodes[faces]
    fn = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])  # outward, |fn| = 2 × area
    bnodes = unique_values(faces)
    k = bnodes[np.argmin(np.linalg.norm(mesh.nodes[bnodes] - np.asarray(point_mm, float),
                                        axis=1))]
    normal = fn[(faces == k).any(axis=1)].sum(axis=0)
    normal /= np.linalg.norm(normal)
    return mesh.nodes[k] - depth_mm * normal
