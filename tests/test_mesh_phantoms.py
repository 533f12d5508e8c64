"""Procedural mouse and gummy-bear phantoms: closed meshes in the simulator's scene, and (slow,
`make validate`) full-resolution scans meshed at two node distances with previews."""

import json
import tomllib
from pathlib import Path

import numpy as np
import pytest

from dotshell.fem.meshes import TriangleSurface, closed_manifold_problems

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("kind,size_mm", [("mouse", (27.2, 11.6, 10.5)),
                                          ("gummy-bear", (12.0, 7.2, 18.3))])
def test_phantom_mesh_is_closed_and_stands_on_the_plate(kind, size_mm):
    from dotshell_sim.phantoms import phantom_mesh, phantom_volume_mm3

    v, f = phantom_mesh(kind)
    assert closed_manifold_problems(TriangleSurface(v, f)) == []
    np.testing.assert_allclose(np.ptp(v, axis=0), size_mm, atol=0.3)
    assert v[:, 2].min() == pytest.approx(0.0, abs=1e-6)
    assert phantom_volume_mm3(kind) > 0.3 * np.prod(size_mm) / 2


def test_phantom_scene_is_ray_cast_with_its_material():
    from dotshell_sim.scene import MATERIALS, build_scene

    scene = build_scene({"kind": "mouse", "radius_mm": 1.0, "height_mm": 1.0,
                         "offset_mm": [0.0, 0.0], "material": "matte-white"},
                        {"radius_mm": 30.0, "material": "plate"},
                        {"distance_mm": 0.0, "material": "background"}).at(0.0)
    origins = np.array([[-2.0, 0.0, 50.0], [0.0, 20.0, 50.0]])
    t, normals, mat = scene.intersect(origins, np.array([[0, 0, -1.0], [0, 0, -1.0]]))
    assert 50 - t[0] == pytest.approx(10.0, abs=0.3)  # the body's top (≈10 mm)
    assert normals[0, 2] > 0.9 and scene.materials[mat[0]].name == "matte-white"
    assert 50 - t[1] == pytest.approx(0.0, abs=1e-4)  # beside it: the plate
    gummy = MATERIALS["gummy"]
    try:
        import dotshell_sim.subsurface  # noqa: F401
        assert gummy.scattering is not None and gummy.scattering.n == pytest.approx(1.45)
    except ImportError:  # the opaque stand-in
        assert getattr(gummy, "scattering", None) is None


@pytest.mark.parametrize("name", ["sim-mouse-phantom", "sim-gummy-bear"])
def test_phantom_profiles_validate(name):
    from dotshell.plugins import PluginManager
    from dotshell.profile.loader import load_profile

    pm = PluginManager()
    pm.load_entry_points()
    p = load_profile(ROOT / "profiles" / f"{name}.toml", pm)
    assert p.data["mesh"]["after_scan"] and len(p.data["mesh"]["also_node_distances_mm"]) == 1


@pytest.mark.slow
@pytest.mark.parametrize("name,kind", [("sim-mouse-phantom", "mouse"),
                                       ("sim-gummy-bear", "gummy-bear")])
def test_phantom_scanned_and_meshed_at_two_node_distances(name, kind, tmp_path):
    from dotshell.pipeline.scan import scan
    from dotshell.plugins import PluginManager
    from dotshell.profile.loader import load_profile
    from dotshell_sim.phantoms import phantom_volume_mm3

    pm = PluginManager()
    pm.load_entry_points()
    result = scan(load_profile(ROOT / "profiles" / f"{name}.toml", pm), pm, tmp_path)
    meshes = result.report["mesh"]["meshes"]
    assert len(meshes) == 2
    coarse, fine = meshes
    assert fine["volume"]["nodes"] > 2 * coarse["volume"]["nodes"]
    true = phantom_volume_mm3(kind)
    for m in meshes:
        q = m["volume"]
        assert q["inverted_elements"] == 0 and q["joe_liu_min"] >= 0.05
        assert m["surface"]["closed_manifold"]
        # the closed bottom also fills what the camera cannot see under the body
        assert abs(q["volume_mm3"] - true) / true < 0.10
        for rel in m["previews"].values():
            assert (result.run_dir / rel).stat().st_size > 10_000
    assert (result.run_dir / "nirfast" / "mesh.elem").is_file()
    assert (result.run_dir / "toast" / "mesh.msh").is_file()
    if kind == "mouse":  # trans-illuminated at two views (issue 6): the bounds
        n = result.report["normalize"]
        print(json.dumps({k: n[k] for k in ("vs_truth", "masked_total")}, indent=1))
        fres, raw = n["vs_truth"]["diffuse-fresnel"], n["vs_truth"]["none"]
        assert fres["nodes"] > 300
        assert fres["median_abs_pct"] <= 3.0 and fres["p95_abs_pct"] <= 10.0
        assert raw["median_abs_pct"] > 15.0
        assert n["masked_total"]["crease"] > 0 and n["masked_total"]["saturated"] == 0
