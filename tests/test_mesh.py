"""The mesh stage on a scanned cloud: closed surface, valid volume mesh, exports read back,
forward check, and clear errors for bad input."""

import math
import shutil
import tomllib
from pathlib import Path

import numpy as np
import pytest
import tomli_w

from dotshell.errors import DotshellError, ProfileError
from dotshell.fem.meshes import MeshError, TriangleSurface, closed_manifold_problems, signed_volumes_mm3
from dotshell.fem.meshfiles import read_surface, read_volume
from dotshell.plugins import PluginManager

RUN_FILES = ("profile.toml", "manifest.json", "calibration.json", "cloud.ply", "report.json")


def _pm() -> PluginManager:
    pm = PluginManager()
    pm.load_entry_points()
    return pm


def copy_run(src: Path, dst: Path, frames: bool = False, **profile_changes) -> Path:
    """A private copy of a run (the session's small scan is shared, read-only)."""
    if frames:
        shutil.copytree(src, dst, symlinks=True)
    else:
        dst.mkdir(parents=True)
        for name in RUN_FILES:
            shutil.copy(src / name, dst / name)
    prof = tomllib.loads((dst / "profile.toml").read_text())
    prof.update(profile_changes)
    (dst / "profile.toml").write_text(tomli_w.dumps(prof))
    return dst


OPTODES = {"sources_mm": [[7.7, 0.0, 15.0]], "detectors_mm": [[-7.7, 0.0, 15.0],
                                                              [0.0, 7.7, 15.0]]}


@pytest.fixture(scope="module")
def meshed(small_scan, tmp_path_factory):
    from dotshell.pipeline.commands import mesh_run

    run = copy_run(small_scan[0].run_dir, tmp_path_factory.mktemp("mesh") / "run",
                   mesh={"node_distance_mm": 1.0, "optodes": OPTODES},
                   export={"nirfast": {}, "toast": {}, "meshio": {"formats": ["gmsh", "stl"]}})
    return mesh_run(run, _pm())


def test_cylinder_cloud_gives_closed_surface_and_volume_within_1pct(meshed):
    """True section: the whole cylinder, r = 7.7 mm from the plate (z = 0, where the mesher
    closes the bottom the region of interest left open) to the top (30 mm)."""
    entry = meshed.report["mesh"]["meshes"][0]
    run = meshed.run_dir
    surf = read_surface(run / "surface.ply")
    assert closed_manifold_problems(surf) == []
    assert surf.vertices[:, 2].min() == pytest.approx(0.0, abs=1e-6)
    assert np.median(surf.vertices[surf.vertices[:, 2] > 29.0, 2]) == pytest.approx(30.0, abs=0.05)
    r = np.hypot(surf.vertices[:, 0], surf.vertices[:, 1])
    side = (surf.vertices[:, 2] > 2) & (surf.vertices[:, 2] < 28)
    assert abs(np.median(r[side]) - 7.7) < 0.05
    mesh = read_volume(run / "volume.vtu")
    vol = signed_volumes_mm3(mesh.nodes, mesh.tets)
    true = math.pi * 7.7 ** 2 * 30.0
    assert abs(vol.sum() - true) / true < 0.01
    assert (vol > 0).all()
    q = entry["volume"]
    assert q["inverted_elements"] == 0 and q["joe_liu_min"] >= 0.1
    assert q["nodes"] == len(mesh.nodes) and q["elements"] == len(mesh.tets)
    assert abs(q["volume_vs_surface_pct"]) < 1e-3
    assert entry["validation"]["volume_error_pct"] == pytest.approx(
        100 * (vol.sum() - true) / true)
    assert 0.8 < q["edge_length_mm"]["median"] < 1.25  # the node distance asked for
    for name in ("surface_1mm.png", "volume_1mm.png"):
        assert (run / "previews" / name).stat().st_size > 10_000


def test_scanned_mesh_exports_read_back(meshed):
    from dotshell_dotio.nirfast import read_nirfast
    from dotshell_dotio.toast import read_msh, read_qm

    run = meshed.run_dir
    mesh = read_volume(run / "volume.vtu")
    assert set(meshed.report["exports"]) == {"nirfast", "toast", "meshio"}
    nf = read_nirfast(run / "nirfast", "mesh")
    np.testing.assert_allclose(nf.nodes, mesh.nodes, atol=1e-8)
    assert (nf.elements == mesh.tets).all()
    assert (nf.bndvtx == mesh.boundary_nodes).all()
    np.testing.assert_allclose(nf.mua, 0.01)
    np.testing.assert_allclose(nf.kappa, 1 / (3 * 1.01))
    np.testing.assert_allclose(nf.ri, 1.33)
    np.testing.assert_allclose(nf.sources, OPTODES["sources_mm"])
    assert nf.links.tolist() == [[0, 0], [0, 1]]
    tm = read_msh(run / "toast" / "mesh.msh")
    assert (tm.elements == mesh.tets).all() and (tm.boundary == mesh.boundary_nodes).all()
    assert (signed_volumes_mm3(tm.nodes, tm.elements) > 0).all()
    np.testing.assert_allclose(read_qm(run / "toast" / "mesh.qm").detectors_mm,
                               OPTODES["detectors_mm"])
    assert (run / "meshio" / "volume.msh").is_file() and (run / "meshio" / "surface.stl").is_file()


def test_forward_on_the_scanned_mesh(meshed):
    from dotshell.pipeline.commands import forward_run

    out = forward_run(meshed.run_dir)
    # the optode source on the skin is moved 1/μs' = 1 mm inside, as NIRFAST does
    assert 0.9 < 7.7 - math.hypot(*out["source_mm"][:2]) < 1.6
    assert out["negative_nodes"] == 0
    near, far = out["detector_fluence_per_mm2"][1], out["detector_fluence_per_mm2"][0]
    assert near > 2 * far > 0  # 90° round the cylinder sees more light than 180°
    assert (meshed.run_dir / "forward.vtu").is_file()


def test_mesh_after_reprocessing_when_the_profile_asks(small_scan, tmp_path):
    """[mesh] after_scan runs the stage inside finish() (scan and reconstruct), before the
    exporters, which find the volume mesh."""
    from dotshell.pipeline.commands import reconstruct_run

    run = copy_run(small_scan[0].run_dir, tmp_path / "run", frames=True,
                   mesh={"after_scan": True, "node_distance_mm": 2.0, "previews": False},
                   export={"toast": {}})
    result = reconstruct_run(run, _pm())
    q = result.report["mesh"]["meshes"][0]["volume"]
    assert q["inverted_elements"] == 0 and q["nodes"] > 200
    assert result.report["exports"]["toast"] == ["toast/mesh.msh"]
    assert "mesh" in result.report["timings_s"]


# ---- bad input --------------------------------------------------------------------------

def _cloud_run(tmp_path: Path, small_scan, points: np.ndarray) -> Path:
    from dotshell.run.ply import write_ply

    run = copy_run(small_scan[0].run_dir, tmp_path / "run", mesh={"previews": False})
    write_ply(run / "cloud.ply", points, view=np.zeros(len(points)))
    return run


def test_too_sparse_cloud_is_a_clear_error(small_scan, tmp_path):
    from dotshell.pipeline.commands import mesh_run

    pts = np.random.default_rng(0).normal(size=(150, 3)) * 5 + [0, 0, 15]
    with pytest.raises(MeshError, match="too sparse to close a surface"):
        mesh_run(_cloud_run(tmp_path, small_scan, pts), _pm())


def test_one_sided_cloud_is_a_clear_error(small_scan, tmp_path):
    from dotshell.pipeline.commands import mesh_run

    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.uniform(-8, 8, 20000), np.zeros(20000), rng.uniform(1, 20, 20000)])
    run = _cloud_run(tmp_path, small_scan, pts)
    prof = tomllib.loads((run / "profile.toml").read_text())
    prof["mesh"]["close_bottom"] = False
    (run / "profile.toml").write_text(tomli_w.dumps(prof))
    with pytest.raises(MeshError, match="covers only one side"):
        mesh_run(run, _pm())


def test_open_surface_that_cannot_be_repaired_is_a_clear_error():
    from dotshell.settings import validate_settings
    from dotshell_meshing.surface import repair_closed
    from dotshell_meshing.volume import SETTINGS, TetgenVolumeMesher

    x, y = np.meshgrid(np.linspace(0, 10, 11), np.linspace(0, 10, 11))
    v = np.column_stack([x.ravel(), y.ravel(), np.zeros(121)])
    tri = [[a, a + 1, a + 12] for a in range(109) if a % 11 != 10]
    tri += [[a, a + 12, a + 11] for a in range(109) if a % 11 != 10]
    sheet = TriangleSurface(v, tri)
    with pytest.raises(MeshError, match="could not be repaired to a closed manifold"):
        repair_closed(sheet)
    with pytest.raises(MeshError, match="needs a closed, outward-oriented surface"):
        TetgenVolumeMesher(validate_settings(SETTINGS, {}, "t")).volume(sheet, 1.0)


def test_node_distance_zero_is_a_clear_error(meshed, tmp_path):
    from dotshell.cli.app import main
    from dotshell.pipeline.commands import mesh_run
    from dotshell.profile.loader import validate_profile

    with pytest.raises(MeshError, match="node distance must be a positive number"):
        mesh_run(meshed.run_dir, _pm(), node_distance_mm=0.0)
    raw = tomllib.loads((meshed.run_dir / "profile.toml").read_text())
    raw["mesh"]["node_distance_mm"] = 0.0
    with pytest.raises(ProfileError, match=r"mesh.node_distance_mm"):
        validate_profile(raw, _pm(), "p.toml")
    assert main(["mesh", str(meshed.run_dir), "--node-distance", "0"]) == 2
    assert issubclass(MeshError, DotshellError)


@pytest.mark.slow
def test_full_resolution_cylinder_mesh(tmp_path):
    """`make validate`: the 1280×1024, 12-view metal cylinder meshed at 1 mm at the end of the
    scan, with NIRFAST and TOAST files."""
    from dotshell.pipeline.scan import scan
    from dotshell.profile.loader import load_profile

    root = Path(__file__).resolve().parents[1]
    pm = _pm()
    profile = load_profile(root / "profiles" / "sim-metal-cylinder.toml", pm,
                           ["mesh.after_scan=true", "mesh.node_distance_mm=1.0",
                            "export.nirfast={}", "export.toast={}"])
    result = scan(profile, pm, tmp_path)
    entry = result.report["mesh"]["meshes"][0]
    assert abs(entry["validation"]["volume_error_pct"]) < 1.0
    assert entry["volume"]["inverted_elements"] == 0 and entry["volume"]["joe_liu_min"] >= 0.1
    assert (result.run_dir / "nirfast" / "mesh.node").is_file()
    assert (result.run_dir / "toast" / "mesh.msh").is_file()


def test_the_footprint_raster_is_closed_and_filled_as_scipy_does():
    """The closed bottom's footprint (closing with two iterations, holes filled, 4-neighbour
    cross) without scipy.ndimage, whose import cost the mesh process ~0.25 s: the same masks
    as scipy's on random rasters, including sets touching the edges, and on a ring."""
    from scipy import ndimage

    from dotshell_meshing.surface import closing, fill_holes

    rng = np.random.default_rng(7)
    for _ in range(500):
        mask = rng.random(rng.integers(1, 30, 2)) < rng.uniform(0.05, 0.9)
        iterations = int(rng.integers(1, 4))
        assert np.array_equal(closing(mask, iterations),
                              ndimage.binary_closing(mask, iterations=iterations))
        assert np.array_equal(fill_holes(mask), ndimage.binary_fill_holes(mask))
    y, x = np.mgrid[:41, :41]
    ring = np.abs(np.hypot(x - 20, y - 20) - 15) < 1
    filled = fill_holes(closing(ring, 2))
    assert filled[20, 20] and not filled[0, 0]
    assert filled.sum() == ndimage.binary_fill_holes(ndimage.binary_closing(
        ring, iterations=2)).sum() > 600


def test_a_cloud_naming_views_the_run_does_not_list_has_no_viewpoints():
    """ViewCentres.lists_every is np.isin(views, indices).all() (a table of the listed views
    instead of a sort: 0.075 s of the mesh process for 5.5 M points), float and integer view
    numbers, values between or beyond the listed ones, NaN, chunk borders."""
    from dotshell.pipeline.mesh import ViewCentres

    centres = ViewCentres(np.array([0, 2, 3, 7]), np.arange(12.0).reshape(4, 3))
    rng = np.random.default_rng(5)
    for values in ([0, 2, 3, 7], [0, 1], [7, 8], [2.5], [-1], [np.nan], [3.0, 7.0], []):
        for dtype in (np.float32, np.int64):
            if dtype is np.int64 and any(not float(v).is_integer() for v in values):
                continue
            views = np.concatenate([rng.choice([0, 2, 3, 7], 2500), values]).astype(dtype)
            want = bool(np.isin(views, centres.indices).all())
            assert centres.lists_every(views, chunk=1000) == want, (values, dtype)
            assert (centres.per_point(views) is None) == (not want)
    vp = centres.per_point(np.array([7, 0, 3], np.float32))
    np.testing.assert_array_equal(vp[0:3], [[9, 10, 11], [0, 1, 2], [6, 7, 8]])
    # view indices too large for a table of them: each point's centre all the same
    far = ViewCentres(np.array([-5, 3, 2_000_000]), np.arange(9.0).reshape(3, 3))
    vp = far.per_point(np.array([2_000_000, -5, 3, 3], np.float64))
    np.testing.assert_array_equal(vp[1:4], [[0, 1, 2], [3, 4, 5], [3, 4, 5]])
    np.testing.assert_array_equal(vp[0:1], [[6, 7, 8]])


def test_a_mesh_file_that_cannot_be_written_fails_the_step(small_scan, tmp_path, monkeypatch):
    """The meshes are written in a thread while the previews are drawn: a write that fails
    (here a full disk at volume.vtu) fails the step as before, and the run keeps no volume."""
    import errno

    import dotshell.pipeline.mesh as mesh_module
    from dotshell.pipeline.commands import mesh_run

    def full_disk(path, mesh):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(mesh_module, "write_volume", full_disk)
    run = copy_run(small_scan[0].run_dir, tmp_path / "run", mesh={"node_distance_mm": 2.0})
    with pytest.raises((OSError, DotshellError), match="No space left on device"):
        mesh_run(run, _pm())
    assert not list(run.rglob("volume.vtu"))


def test_the_thinning_of_an_empty_or_small_cloud():
    """The chunked thinning (within runtime.process.heap_reused) of no points is no points; a
    cloud under the chunked size is kept as it is, with its viewpoints as normals."""
    from dotshell.runtime.compat import import_open3d
    from dotshell_meshing.surface import _thinned_cloud

    o3d = import_open3d()
    assert len(_thinned_cloud(o3d, np.zeros((0, 3), np.float32), None, 0.1).points) == 0
    pts = np.random.default_rng(2).uniform(0, 10, (1000, 3)).astype(np.float32)
    cloud = _thinned_cloud(o3d, pts, np.tile([0.0, 0.0, 50.0], (1000, 1)), 0.1)
    assert len(cloud.points) == 1000 and np.allclose(np.asarray(cloud.normals)[:, 2], 50.0)
