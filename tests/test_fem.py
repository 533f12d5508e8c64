"""FEM building blocks and the CW diffusion forward check against the analytic sphere."""

import math

import numpy as np
import pytest

from dotshell.fem.meshes import (MeshError, TetMesh, TriangleSurface, boundary_faces,
                          closed_manifold_problems, element_containing, enclosed_volume_mm3,
                          joe_liu_quality, min_dihedral_deg, orient_positive, quality_report,
                          signed_volumes_mm3, unique_rows)
from dotshell.fem.forward import (move_inside, robin_A, solve_cw, sphere_point_source_fluence,
                              system_matrix)

REGULAR = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)


def test_regular_tetrahedron_measures():
    tets = orient_positive(REGULAR, np.array([[0, 1, 2, 3]]))
    assert signed_volumes_mm3(REGULAR, tets)[0] == pytest.approx(8 / 3)
    assert joe_liu_quality(REGULAR, tets)[0] == pytest.approx(1.0)
    assert min_dihedral_deg(REGULAR, tets)[0] == pytest.approx(math.degrees(math.acos(1 / 3)))
    flat = REGULAR.copy()
    flat[3] = (flat[0] + flat[1] + flat[2]) / 3 + [0, 0, 1e-3]
    assert joe_liu_quality(flat, tets)[0] < 0.01


def test_orientation_and_boundary_faces_point_outward():
    tets = np.array([[0, 1, 2, 3]])
    assert signed_volumes_mm3(REGULAR, tets)[0] < 0
    pos = orient_positive(REGULAR, tets)
    assert signed_volumes_mm3(REGULAR, pos)[0] > 0
    surf = TriangleSurface(REGULAR, boundary_faces(pos))
    assert enclosed_volume_mm3(surf) == pytest.approx(8 / 3)
    assert closed_manifold_problems(surf) == []
    holed = TriangleSurface(REGULAR, surf.triangles[:3])
    assert "boundary edges" in closed_manifold_problems(holed)[0]


def test_element_containing_and_outside_point():
    mesh = TetMesh(REGULAR, orient_positive(REGULAR, np.array([[0, 1, 2, 3]])))
    k, w = element_containing(mesh, [0.0, 0.0, 0.0])
    assert k == 0 and np.allclose(w, 0.25)
    with pytest.raises(MeshError, match="outside the mesh"):
        element_containing(mesh, [5.0, 0.0, 0.0])


def test_robin_factor_matches_fresnel_values():
    assert robin_A(1.0) == pytest.approx(1.0)
    # NIRFAST's Fresnel-derived A grows with n; ~2.35 for water-like tissue
    assert robin_A(1.33) == pytest.approx(2.348, abs=2e-3)
    assert robin_A(1.4) > robin_A(1.33)


def cube_grid(n: int, jitter_mm: float = 0.0, seed: int = 0) -> TetMesh:
    """n × n × n unit cubes (mm), each split into the 6 tetrahedra around its main diagonal
    (Kuhn's subdivision, conforming between cubes): 12 n² boundary faces. Interior nodes moved
    by up to ``jitter_mm`` so that no two elements are alike."""
    axis = np.arange(n + 1)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    index = lambda p: (p[..., 0] * (n + 1) + p[..., 1]) * (n + 1) + p[..., 2]  # noqa: E731
    corners = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    unit = np.eye(3, dtype=int)
    tets = []
    for a, b, _ in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
        path = [np.zeros(3, int), unit[a], unit[a] + unit[b], np.ones(3, int)]
        tets.append(np.stack([index(corners + step) for step in path], axis=1))
    nodes = grid.astype(float)
    inner = ((grid > 0) & (grid < n)).all(axis=1)
    nodes[inner] += np.random.default_rng(seed).uniform(-jitter_mm, jitter_mm, (inner.sum(), 3))
    return TetMesh(nodes, orient_positive(nodes, np.concatenate(tets)))


def coo_system_matrix(mesh: TetMesh, mua: np.ndarray, kappa: np.ndarray, A: float):
    """The system matrix built the straightforward way (dotshell's before issue 16): boundary
    faces by np.unique of the sorted face rows, element matrices by einsum, COO → CSR."""
    import scipy.sparse as sp

    t = mesh.tets
    faces = t[:, [0, 2, 1, 0, 1, 3, 1, 2, 3, 0, 3, 2]].reshape(-1, 3)
    _, inv, count = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True,
                              return_counts=True)
    f = faces[count[inv.ravel()] == 1]
    p = mesh.nodes[t]
    jac = np.stack([p[:, k] - p[:, 0] for k in (1, 2, 3)], axis=1)  # rows e1, e2, e3
    g123 = np.linalg.inv(jac).transpose(0, 2, 1)  # ∇λk: the columns of J⁻¹
    grads = np.concatenate([-g123.sum(axis=1, keepdims=True), g123], axis=1)
    vol = np.linalg.det(jac) / 6.0
    stiff = np.einsum("m,mik,mjk->mij", kappa[t].mean(axis=1) * vol, grads, grads)
    mass = (mua[t].mean(axis=1) * vol / 20.0)[:, None, None] * (np.ones((4, 4)) + np.eye(4))
    v = mesh.nodes[f]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    bnd = (area / 12.0 / (2.0 * A))[:, None, None] * (np.ones((3, 3)) + np.eye(3))
    rows = np.concatenate([np.repeat(t, 4, axis=1).ravel(), np.repeat(f, 3, axis=1).ravel()])
    cols = np.concatenate([np.tile(t, (1, 4)).ravel(), np.tile(f, (1, 3)).ravel()])
    data = np.concatenate([(stiff + mass).ravel(), bnd.ravel()])
    n = len(mesh.nodes)
    return sp.coo_matrix((data, (rows, cols)), shape=(n, n)).tocsr(), f


def assert_same_system(mesh: TetMesh, seed: int = 1) -> None:
    """system_matrix equals coo_system_matrix to rounding, with the same pattern and the same
    boundary faces (as node sets and in orientation)."""
    rng = np.random.default_rng(seed)
    n = len(mesh.nodes)
    mua, kappa = rng.uniform(0.005, 0.05, n), rng.uniform(0.2, 0.4, n)
    expected, faces = coo_system_matrix(mesh, mua, kappa, 2.35)
    got = system_matrix(mesh, mua, kappa, 2.35)
    assert np.array_equal(got.indptr, expected.indptr)
    assert np.array_equal(got.indices, expected.indices)
    assert np.abs(got.data - expected.data).max() <= 1e-13 * np.abs(expected.data).max()
    assert sorted(map(tuple, mesh.boundary_faces)) == sorted(map(tuple, faces))


@pytest.mark.parametrize("n", [1, 3])
def test_boundary_faces_and_assembly_of_a_cube_grid(n):
    mesh = cube_grid(n, jitter_mm=0.1)
    assert len(mesh.tets) == 6 * n ** 3
    assert signed_volumes_mm3(mesh.nodes, mesh.tets).sum() == pytest.approx(n ** 3)  # none flipped
    assert len(mesh.boundary_faces) == 12 * n ** 2
    surf = TriangleSurface(mesh.nodes, mesh.boundary_faces)
    assert closed_manifold_problems(surf) == []
    assert enclosed_volume_mm3(surf) == pytest.approx(n ** 3)  # outward, the grid's volume
    assert_same_system(mesh)
    flipped = TetMesh(mesh.nodes, mesh.tets[:, [0, 1, 3, 2]])
    with pytest.raises(MeshError, match=f"{6 * n ** 3} elements are inverted"):
        system_matrix(flipped, np.full(len(mesh.nodes), 0.01), np.full(len(mesh.nodes), 0.3),
                      2.35)


@pytest.mark.parametrize("n", [1, 3, 6])
def test_boundary_faces_by_sorting_are_the_kernels_faces(n):
    """The numpy boundary (the mesh process and previews, which start no numba) gives the
    kernel's faces in the kernel's order, on cube grids and on a cut half (an inner cut)."""
    from dotshell.fem.meshes import boundary_faces_by_sorting

    mesh = cube_grid(n, jitter_mm=0.1)
    got = boundary_faces_by_sorting(mesh.tets)
    assert len(got) == 12 * n ** 2 and np.array_equal(got, boundary_faces(mesh.tets))
    half = mesh.tets[mesh.nodes[mesh.tets].mean(axis=1)[:, 1] <= n / 2]
    assert np.array_equal(boundary_faces_by_sorting(half), boundary_faces(half))
    assert boundary_faces_by_sorting(np.empty((0, 4), int)).shape == (0, 3)


@pytest.fixture(scope="module")
def sphere_mesh():
    """Sphere of radius 10 mm: icosphere surface (0.66 mm edges) + tetgen at 1.2 mm."""
    import pyvista as pv

    from dotshell.settings import validate_settings
    from dotshell_meshing.volume import SETTINGS, TetgenVolumeMesher

    ico = pv.Icosphere(radius=10.0, nsub=4)
    surf = TriangleSurface(ico.points, ico.faces.reshape(-1, 4)[:, 1:])
    return TetgenVolumeMesher(validate_settings(SETTINGS, {}, "test")).volume(surf, 1.2), surf


def test_assembly_matches_coo_construction_on_the_sphere(sphere_mesh):
    assert_same_system(sphere_mesh[0])


def test_boundary_slivers_peeled_are_those_the_definition_names():
    """peel_boundary_slivers drops, round by round, the elements with two or more faces no
    other element shares and a Joe–Liu quality below the bound: against a plain count of each
    face's elements, on a cube grid with every node moved at random (its corners and edges
    have such elements; the higher bounds peel more of them, round after round)."""
    from collections import Counter

    from dotshell.fem.faces import TET_FACES, unshared_faces
    from dotshell_meshing.volume import peel_boundary_slivers

    mesh = cube_grid(4)
    nodes = mesh.nodes + np.random.default_rng(3).normal(0.0, 0.12, mesh.nodes.shape)
    tets = mesh.tets

    def alone_faces(tets):
        faces = [tuple(sorted(f)) for t in tets.tolist() for f in np.array(t)[TET_FACES]]
        count = Counter(faces)
        return np.array([count[f] == 1 for f in faces]).reshape(-1, 4)

    def reference(tets, bound):
        for _ in range(5):
            drop = (alone_faces(tets).sum(axis=1) >= 2) & (joe_liu_quality(nodes, tets) < bound)
            if not drop.any():
                break
            tets = tets[~drop]
        return tets

    sizes = set()
    for bound in (0.05, 0.6, 0.7, 0.8, 1.01):
        got = peel_boundary_slivers(nodes, tets, bound)
        assert np.array_equal(got, reference(tets, bound)), bound
        sizes.add(len(got))
    assert len(sizes) >= 3 and min(sizes) < len(tets) - 50  # some bounds peel, over rounds
    assert np.array_equal(unshared_faces(tets), alone_faces(tets))
    assert np.array_equal(unshared_faces(tets + 2_000_000), alone_faces(tets))  # lexsort branch


def test_sphere_mesh_quality(sphere_mesh):
    mesh, surf = sphere_mesh
    q = quality_report(mesh, surf)
    assert q["nodes"] <= 20_000 and q["inverted_elements"] == 0
    assert q["joe_liu_min"] >= 0.1
    assert abs(q["volume_vs_surface_pct"]) < 1e-6


def test_forward_matches_analytic_sphere_on_the_boundary(sphere_mesh):
    """μa = 0.01/mm, μs' = 1/mm, n = 1.33, point source at the centre: the median relative
    difference on the boundary nodes is within 2 % (measured 0.5 % at 6,800 nodes)."""
    mesh, _ = sphere_mesh
    res = solve_cw(mesh, [0.0, 0.0, 0.0], 0.01, 1.0, 1.33)
    b = mesh.boundary_nodes
    r = np.linalg.norm(mesh.nodes[b], axis=1)
    exact = sphere_point_source_fluence(r, 10.0, 0.01, 1.0, 1.33)
    rel = np.abs(res.fluence[b] - exact) / exact
    assert np.median(rel) < 0.02
    assert np.percentile(rel, 95) < 0.05
    assert (res.fluence > 0).all()
    # a wrong boundary condition (A = 1, no Fresnel reflection) is clearly distinguishable
    wrong = sphere_point_source_fluence(r, 10.0, 0.01, 1.0, 1.0)
    assert np.median(np.abs(wrong - exact) / exact) > 0.1


def test_conjugate_gradient_agrees_with_sparse_lu(sphere_mesh):
    """The Jacobi-CG solve of solve_cw against a direct sparse LU of the same system, with a
    heterogeneous μa (a 3× absorbing inclusion) and the source off-centre."""
    from scipy.sparse.linalg import splu

    mesh, _ = sphere_mesh
    mua = np.where(np.linalg.norm(mesh.nodes - [4.0, 0.0, 0.0], axis=1) < 3.0, 0.03, 0.01)
    res = solve_cw(mesh, [-3.0, 2.0, 1.0], mua, 1.0, 1.33)
    kappa = 1.0 / (3.0 * (mua + 1.0))
    q = np.zeros(len(mesh.nodes))
    q[mesh.tets[res.element]] = element_containing(mesh, res.source_mm)[1]
    lu = splu(system_matrix(mesh, mua, kappa, res.A).tocsc(), permc_spec="COLAMD").solve(q)
    assert np.abs(res.fluence - lu).max() < 1e-9 * lu.max()
    boundary = mesh.boundary_nodes
    assert np.median(np.abs(res.fluence[boundary] / lu[boundary] - 1.0)) < 1e-8


def test_forward_rejects_bad_input(sphere_mesh):
    mesh, _ = sphere_mesh
    with pytest.raises(MeshError, match="outside the mesh"):
        solve_cw(mesh, [0.0, 0.0, 20.0], 0.01, 1.0, 1.33)
    with pytest.raises(MeshError, match="μs' > 0"):
        solve_cw(mesh, [0.0, 0.0, 0.0], 0.01, 0.0, 1.33)
    inside = move_inside(mesh, [0.0, 0.0, 10.5], 1.0)
    assert np.linalg.norm(inside) == pytest.approx(9.0, abs=0.05)


@pytest.mark.parametrize("shape, high, dtype", [((5000, 2), 300, np.int64),
                                                ((4000, 3), 40, np.int32), ((0, 3), 1, np.int64)])
def test_unique_rows_is_numpys_row_unique(shape, high, dtype):
    rows = np.random.default_rng(3).integers(0, high, shape).astype(dtype)
    want = np.unique(rows, axis=0, return_inverse=True, return_counts=True)
    got = unique_rows(rows, return_inverse=True, return_counts=True)
    assert got[0].dtype == want[0].dtype and got[0].shape == want[0].shape
    for a, b in zip(got, want):
        assert np.array_equal(np.ravel(a), np.ravel(b))
    if len(rows):
        assert (want[2] > 1).any()  # the rows repeat: the counts are checked
