"""NIRFAST, TOAST and meshio exporters: every file written is read back field by field."""

from pathlib import Path

import numpy as np
import pytest

from dotshell.fem.meshes import TetMesh, TriangleSurface, signed_volumes_mm3
from dotshell.fem.meshfiles import (Optodes, read_optodes, read_surface, read_volume, write_optodes,
                                write_surface, write_volume)


@pytest.fixture(scope="module")
def mesh_dir(tmp_path_factory) -> Path:
    """A run-like directory with a small sphere mesh (tetgen), optics and optodes."""
    import pyvista as pv

    from dotshell.settings import validate_settings
    from dotshell_meshing.volume import SETTINGS, TetgenVolumeMesher

    ico = pv.Icosphere(radius=5.0, nsub=2)
    surf = TriangleSurface(ico.points, ico.faces.reshape(-1, 4)[:, 1:])
    mesh = TetgenVolumeMesher(validate_settings(SETTINGS, {}, "test")).volume(surf, 1.5)
    n = len(mesh.nodes)
    rng = np.random.default_rng(1)
    mesh.point_data = {"region": np.where(mesh.nodes[:, 2] > 0, 1, 2).astype(np.int32),
                       "mua_per_mm": rng.uniform(0.005, 0.02, n),
                       "musp_per_mm": rng.uniform(0.5, 1.5, n),
                       "refractive_index": np.full(n, 1.37)}
    d = tmp_path_factory.mktemp("meshdir")
    write_volume(d / "volume.vtu", mesh)
    write_surface(d / "surface.ply", surf)
    write_optodes(d / "optodes.json", Optodes([[0, 0, 5.0], [5.0, 0, 0]],
                                              [[0, 0, -5.0], [-5.0, 0, 0], [0, 5.0, 0]],
                                              [[0, 0], [0, 1], [1, 2]]))
    return d


def _export(name: str, d: Path, **settings):
    from dotshell.plugins import PluginManager

    pm = PluginManager()
    pm.load_entry_points()
    return pm.create("exporter", name, settings, None, "test").export(d)


def test_run_files_round_trip(mesh_dir):
    mesh = read_volume(mesh_dir / "volume.vtu")
    assert len(mesh.tets) > 100 and (signed_volumes_mm3(mesh.nodes, mesh.tets) > 0).all()
    assert set(mesh.point_data) == {"region", "mua_per_mm", "musp_per_mm", "refractive_index"}
    surf = read_surface(mesh_dir / "surface.ply")
    assert len(surf.triangles) == 320
    o = read_optodes(mesh_dir / "optodes.json")
    assert o.links.tolist() == [[0, 0], [0, 1], [1, 2]]


def test_nirfast_files_read_back_field_by_field(mesh_dir):
    from dotshell_dotio.nirfast import kappa_mm, read_nirfast

    paths = _export("nirfast", mesh_dir)
    assert sorted(p.suffix for p in paths) == [".elem", ".link", ".meas", ".node", ".param",
                                               ".region", ".source"]
    mesh = read_volume(mesh_dir / "volume.vtu")
    pd = mesh.point_data
    nf = read_nirfast(mesh_dir / "nirfast", "mesh")
    assert (mesh_dir / "nirfast" / "mesh.param").read_text().splitlines()[0] == "stnd"
    assert "\t" in (mesh_dir / "nirfast" / "mesh.node").read_text().splitlines()[0]
    np.testing.assert_allclose(nf.nodes, mesh.nodes, rtol=1e-9, atol=1e-9)
    assert (nf.bndvtx == mesh.boundary_nodes.astype(int)).all()
    assert nf.bndvtx.sum() > 0 and (nf.bndvtx == 0).sum() > 0
    assert (nf.elements == mesh.tets).all()  # 1-based in the file
    assert (signed_volumes_mm3(nf.nodes, nf.elements) > 0).all()
    np.testing.assert_allclose(nf.mua, pd["mua_per_mm"], rtol=1e-9)
    np.testing.assert_allclose(nf.kappa, kappa_mm(pd["mua_per_mm"], pd["musp_per_mm"]), rtol=1e-9)
    np.testing.assert_allclose(1 / (3 * nf.kappa) - nf.mua, pd["musp_per_mm"], rtol=1e-8)
    np.testing.assert_allclose(nf.ri, 1.37)
    assert (nf.region == pd["region"]).all()
    np.testing.assert_allclose(nf.sources, [[0, 0, 5.0], [5.0, 0, 0]])
    np.testing.assert_allclose(nf.detectors, [[0, 0, -5.0], [-5.0, 0, 0], [0, 5.0, 0]])
    assert nf.links.tolist() == [[0, 0], [0, 1], [1, 2]]


def test_toast_files_read_back_field_by_field(mesh_dir):
    from dotshell_dotio.nirfast import kappa_mm
    from dotshell_dotio.toast import read_msh, read_qm

    paths = _export("toast", mesh_dir, dir="toastfiles", stem="sphere")
    assert [p.name for p in paths] == ["sphere.msh", "sphere.qm"]
    mesh = read_volume(mesh_dir / "volume.vtu")
    pd = mesh.point_data
    tm = read_msh(mesh_dir / "toastfiles" / "sphere.msh")
    np.testing.assert_allclose(tm.nodes, mesh.nodes, rtol=1e-9, atol=1e-9)
    assert (tm.boundary == mesh.boundary_nodes).all()
    assert set(tm.element_types) == {"c"}
    assert (tm.elements == mesh.tets).all()
    assert (signed_volumes_mm3(tm.nodes, tm.elements) > 0).all()  # positively oriented
    assert (tm.region == pd["region"] - 1).all()
    np.testing.assert_allclose(tm.params["MUA"], pd["mua_per_mm"], rtol=1e-9)
    np.testing.assert_allclose(tm.params["KAPPA"], kappa_mm(pd["mua_per_mm"],
                                                            pd["musp_per_mm"]), rtol=1e-9)
    np.testing.assert_allclose(tm.params["N"], 1.37)
    qm = read_qm(mesh_dir / "toastfiles" / "sphere.qm")
    np.testing.assert_allclose(qm.sources_mm, [[0, 0, 5.0], [5.0, 0, 0]])
    np.testing.assert_allclose(qm.detectors_mm, [[0, 0, -5.0], [-5.0, 0, 0], [0, 5.0, 0]])
    assert qm.links.tolist() == [[0, 0], [0, 1], [1, 2]]


def test_mesh_without_optics_gets_the_profile_defaults_in_both_formats(mesh_dir, tmp_path):
    """NIRFAST and TOAST fill a mesh without per-node properties from one place: the
    profile's [mesh.optics] defaults (μa 0.01/mm, μs' 1/mm, n 1.33), region 1."""
    from dotshell.profile.mesh import MESH_SCHEMA
    from dotshell_dotio.nirfast import read_nirfast, write_nirfast
    from dotshell_dotio.optics import kappa_mm
    from dotshell_dotio.toast import msh_text, read_msh

    mesh = read_volume(mesh_dir / "volume.vtu")
    mesh.point_data = {}
    defaults = {k: s.default for k, s in MESH_SCHEMA["optics"].schema.items()}
    write_nirfast(tmp_path, "bare", mesh, Optodes([], [], []))
    nf = read_nirfast(tmp_path, "bare")
    (tmp_path / "bare.msh").write_text(msh_text(mesh))
    tm = read_msh(tmp_path / "bare.msh")
    kappa = kappa_mm(defaults["mua_per_mm"], defaults["musp_per_mm"])
    np.testing.assert_allclose(nf.mua, defaults["mua_per_mm"])
    np.testing.assert_allclose(nf.kappa, kappa)
    np.testing.assert_allclose(nf.ri, defaults["refractive_index"])
    assert (nf.region == 1).all() and (tm.region == 0).all()
    np.testing.assert_allclose(tm.params["MUA"], nf.mua)
    np.testing.assert_allclose(tm.params["KAPPA"], nf.kappa)
    np.testing.assert_allclose(tm.params["N"], nf.ri)


def test_meshio_formats_read_back(mesh_dir, capfd):
    import meshio

    paths = _export("meshio", mesh_dir, formats=["vtu", "vtk", "gmsh", "medit", "stl", "ply",
                                                 "obj"])
    assert len(paths) == 7
    assert "Warning" not in capfd.readouterr().err  # meshio's own print (64-bit PLY indices)
    mesh = read_volume(mesh_dir / "volume.vtu")
    surf = read_surface(mesh_dir / "surface.ply")
    for p in paths:
        m = meshio.read(p)
        if "tetra" in m.cells_dict:
            np.testing.assert_allclose(m.points, mesh.nodes, rtol=1e-6, atol=1e-6)
            assert (m.cells_dict["tetra"] == mesh.tets).all(), p.name
            if p.suffix in (".vtu", ".vtk"):
                np.testing.assert_allclose(m.point_data["mua_per_mm"], mesh.point_data["mua_per_mm"])
                assert (m.point_data["boundary"] == mesh.boundary_nodes).all()
        else:  # surfaces: same triangles by position (STL stores corners per facet)
            got = np.sort(np.round(m.points[m.cells_dict["triangle"]], 4).reshape(-1, 9), axis=0)
            want = np.sort(np.round(surf.vertices[surf.triangles], 4).reshape(-1, 9), axis=0)
            np.testing.assert_allclose(got, want, atol=1e-4)


def test_unknown_meshio_format_is_a_clear_error(mesh_dir):
    from dotshell.errors import DotshellError

    with pytest.raises(DotshellError, match="'xyz' is not a supported format"):
        _export("meshio", mesh_dir, formats=["xyz"])


def test_exporter_without_a_volume_mesh_says_what_to_run(tmp_path):
    from dotshell.errors import RunError

    with pytest.raises(RunError, match="dotshell mesh RUN"):
        _export("nirfast", tmp_path)


def test_surface_ply_is_written_without_a_printed_warning(tmp_path, capfd):
    """int64 triangle indices (numpy's default) are written as PLY's int32 without meshio's
    'Warning: PLY doesn't support 64-bit integers' on the terminal (printed by meshio itself,
    so the log flags cannot hide it)."""
    nodes = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    tris = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int64)
    write_surface(tmp_path / "s.ply", TriangleSurface(nodes, tris))
    assert "Warning" not in capfd.readouterr().err
    back = read_surface(tmp_path / "s.ply")
    assert np.array_equal(back.triangles, tris) and np.allclose(back.vertices, nodes)
