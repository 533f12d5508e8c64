"""Trans-illumination normalization: mapping onto the surface, normalizers, outputs, errors.

The mapping tests render exact images of spheres analytically (ray–sphere intersection, the
diffusion-theory exit radiance of dotshell.fem.optics) and map them onto icosphere meshes, so the
true I0 of every node is known independently of the simulator plugin.
"""

from __future__ import annotations

import csv
import json
import shutil

import cv2
import numpy as np
import pytest

from dotshell.fem.meshes import TriangleSurface
from dotshell.geometry.calibration import RigCalibration
from dotshell.geometry.lens import lens_from_fov
from dotshell.geometry.surface_map import (OCCLUDED, OK, SATURATED,
                                           mask_counts, node_intensities, resample_to_image,
                                           view_surface)
from dotshell.fem.optics import exit_radiance_factor

N_TISSUE = 1.4
LENS = lens_from_fov(320, 256, 1600.0, (-0.05, 0.0, 0.0, 0.0, 0.0))
CALIB = RigCalibration(camera=LENS, projector=LENS, R=np.eye(3), T=[80.0, 0.0, 0.0],
                       axis_point=[0.0, 10.0, 200.0], axis_direction=[0.0, -1.0, 0.0])


def icosphere(radius: float, centre, nsub: int = 4) -> TriangleSurface:
    import pyvista as pv

    s = pv.Icosphere(radius=radius, nsub=nsub)
    return TriangleSurface(np.asarray(s.points, float) + np.asarray(centre, float),
                           s.faces.reshape(-1, 4)[:, 1:])


def true_i0(p: np.ndarray) -> np.ndarray:
    """A smooth, strongly varying emission along the normal (sample frame, mm → DN/ms)."""
    return 50.0 * np.exp(0.05 * p[:, 0] + 0.03 * p[:, 2])


def render_spheres(spheres, angle_deg: float, emission=True) -> np.ndarray:
    """Exact image of spheres ((radius, centre) in the sample frame): radiance
    I0 · L(θ)/L(0) (or a uniform 10 DN/ms Lambertian emitter with ``emission=False``)."""
    W, H = LENS.size
    uu, vv = np.meshgrid(np.arange(W), np.arange(H))
    d = LENS.rays(np.column_stack([uu.ravel(), vv.ravel()]).astype(float))
    best = np.full(len(d), np.inf)
    img = np.zeros(len(d))
    for radius, centre in spheres:
        c = CALIB.sample_to_camera(np.asarray(centre, float)[None], angle_deg)[0]
        b = d @ c
        disc = b * b - (c @ c - radius ** 2)
        t = np.where(disc > 0, b - np.sqrt(np.clip(disc, 0, None)), np.inf)
        nearer = t < best
        p = d[nearer] * t[nearer, None]
        cos_out = np.clip(np.einsum("ij,ij->i", (p - c) / radius, -d[nearer]), 0, 1)
        ps = CALIB.camera_to_sample(p, angle_deg)
        img[nearer] = (true_i0(ps) * exit_radiance_factor(cos_out, N_TISSUE)) if emission else 10.0
        best[nearer] = t[nearer]
    return img.reshape(H, W).astype(np.float32)


def _rel(est, truth, sel):
    return np.abs(est[sel] / truth[sel] - 1.0)


def test_diffuse_fresnel_recovers_true_i0_on_a_sphere_lambertian_and_raw_do_not():
    from dotshell_normalizers import (DiffuseFresnelNormalization, LambertianNormalization,
                                      NoNormalization)

    surf = icosphere(8.0, [0.0, 0.0, 10.0])
    img = render_spheres([(8.0, [0.0, 0.0, 10.0])], 30.0)
    view = view_surface(surf, CALIB, 30.0, 0.3)
    light = node_intensities(view, img, np.zeros(img.shape, bool), 2.0)
    ok = light.mask == OK
    assert ok.sum() > 600
    counts = mask_counts(light.mask)
    assert counts["facing_away"] > 1000 and counts["grazing"] > 200 and counts["occluded"] == 0
    truth = true_i0(surf.vertices)
    err = {}
    for name, model in (("fresnel", DiffuseFresnelNormalization(N_TISSUE)),
                        ("lambertian", LambertianNormalization()), ("none", NoNormalization())):
        est = light.intensity / model.orientation_factor(view.sin_beta)
        e = _rel(est, truth, ok)
        err[name] = (np.median(e) * 100, np.percentile(e, 95) * 100)
    assert err["fresnel"][0] < 0.5 and err["fresnel"][1] < 2.5
    assert err["lambertian"][0] > 3.0 and err["lambertian"][1] > 12.0
    assert err["none"][0] > 25.0
    # the raw node intensity carries the orientation factor sin β (times the Fresnel roll-off)
    ratio = light.intensity[ok] / (truth[ok] * exit_radiance_factor(view.sin_beta[ok], N_TISSUE))
    assert np.median(np.abs(ratio / view.sin_beta[ok] - 1)) < 0.005


def test_uniform_lambertian_emitter_gives_intensity_proportional_to_sin_beta():
    surf = icosphere(8.0, [0.0, 0.0, 10.0])
    img = render_spheres([(8.0, [0.0, 0.0, 10.0])], 0.0, emission=False)
    view = view_surface(surf, CALIB, 0.0, 0.3)
    light = node_intensities(view, img, np.zeros(img.shape, bool), 2.0)
    ok = light.mask == OK
    assert np.median(np.abs(light.intensity[ok] / (10.0 * view.sin_beta[ok]) - 1)) < 0.005
    assert np.nanmedian(np.abs(light.radiance[ok] / 10.0 - 1)) < 1e-3


def test_occluded_nodes_are_masked_and_never_used():
    big = (8.0, [0.0, 0.0, 10.0])
    # stage at 0°: the camera looks along the stage frame's -x; a small sphere in front of the
    # big one (towards the camera) hides part of it
    small = (3.0, list(CALIB.camera_to_sample(
        CALIB.sample_to_camera(np.array([[0.0, 0.0, 10.0]]), 0.0) * 0.93, 0.0)[0]))
    a, b = icosphere(*big), icosphere(*small, nsub=3)
    surf = TriangleSurface(np.vstack([a.vertices, b.vertices]),
                           np.vstack([a.triangles, b.triangles + len(a.vertices)]))
    img = render_spheres([big, small], 0.0)
    view = view_surface(surf, CALIB, 0.0, 0.3)
    light = node_intensities(view, img, np.zeros(img.shape, bool), 2.0)
    occluded = light.mask == OCCLUDED
    assert occluded.sum() > 50
    assert np.isnan(light.intensity[occluded]).all()
    # occluded nodes face the camera: without the occlusion test they would have been used
    assert (view.sin_beta[occluded] > 0.3).mean() > 0.9
    ok = light.mask == OK
    truth = true_i0(surf.vertices)
    est = light.intensity / (view.sin_beta * exit_radiance_factor(view.sin_beta, N_TISSUE))
    # nodes next to the hidden patch straddle the small sphere's silhouette: allow a tail
    assert np.median(_rel(est, truth, ok)) < 0.01


def test_saturated_pixels_mask_their_nodes():
    surf = icosphere(8.0, [0.0, 0.0, 10.0])
    img = render_spheres([(8.0, [0.0, 0.0, 10.0])], 0.0)
    sat = img > np.percentile(img[img > 0], 90)
    view = view_surface(surf, CALIB, 0.0, 0.3)
    light = node_intensities(view, img, sat, 2.0)
    assert (light.mask == SATURATED).sum() > 20
    assert np.isnan(light.intensity[light.mask == SATURATED]).all()


def test_flattened_image_is_nan_off_the_sample_and_matches_node_values():
    surf = icosphere(8.0, [0.0, 0.0, 10.0])
    view = view_surface(surf, CALIB, 0.0, 0.3)
    values = true_i0(surf.vertices)
    flat = resample_to_image(view, values)
    inside = np.isfinite(flat)
    assert 0.05 < inside.mean() < 0.9
    assert np.nanmin(flat) >= values.min() - 1e-6 and np.nanmax(flat) <= values.max() + 1e-6


# ---- end to end on the simulated rig ----------------------------------------------------------

def transillumination_profile(exposure_ms: float = 2.0, **trans) -> dict:
    """The reduced metal-cylinder bench with a tissue-like cylinder (the sample's optics for the
    laser), the sim laser, 20 % extra lens vignetting, trans-illumination at two views and the
    mesh stage."""
    from conftest import small_profile_dict

    raw = small_profile_dict(0.25, 6)
    raw["stage"]["settings"]["scene"].update(mua_per_mm=0.01, musp_per_mm=1.0,
                                             refractive_index=1.4)
    raw["camera"]["settings"]["vignetting"] = 0.2
    # the light inside the sample on a 1.5 mm FEM (default 1 mm: the simulator's TetGen and
    # system matrix took a fifth of the scan; the fresnel figures move from 2.19 / 6.03 % to
    # 2.28 / 6.11 %, median / 95th percentile, against the bounds of 3 / 10 %)
    raw["light_source"] = {"backend": "sim-laser", "settings": {"node_spacing_mm": 1.5}}
    raw["transillumination"] = {"enabled": True, "exposure_ms": exposure_ms, "views": [0, 3],
                                "targets_mm": [[0.0, 10.0], [2.0, 15.0]], **trans}
    # the mesh's previews are test_mesh.py's: here the mesh is only the surface to normalize on
    raw["mesh"] = {"after_scan": True, "node_distance_mm": 1.0, "previews": False,
                   "optics": {"refractive_index": 1.4},
                   "optodes": {"detectors_mm": [[7.7, 0.0, 15.0], [-7.7, 0.0, 15.0]]}}
    return raw


@pytest.fixture(scope="module")
def trans_run(tmp_path_factory):
    from conftest import write_profile

    from dotshell.events import EventBus
    from dotshell.pipeline.scan import scan
    from dotshell.plugins import PluginManager
    from dotshell.profile.loader import load_profile

    tmp = tmp_path_factory.mktemp("trans")
    pm = PluginManager()
    pm.load_entry_points()
    events = []
    bus = EventBus()
    bus.subscribe(events.append)
    prof = load_profile(write_profile(tmp / "p.toml", transillumination_profile()), pm)
    return scan(prof, pm, tmp / "runs", bus=bus), events


def test_scan_captures_and_normalizes_within_bounds_on_the_tissue_cylinder(trans_run):
    result, events = trans_run
    run = result.run_dir
    manifest = json.loads((run / "manifest.json").read_text())
    t = manifest["transillumination"]
    assert t["views"] == {"0": ["src_00", "src_01", "dark"], "3": ["src_00", "src_01", "dark"]}
    assert t["flat_field"] == "transillumination/flat.png"
    for v in (0, 3):
        for name in ("src_00", "src_01", "dark"):
            assert (run / "transillumination" / f"view_{v:03d}" / f"{name}.png").is_file()
    n = result.report["normalize"]
    assert n["normalizer"] == "diffuse-fresnel" and n["flat_field"] is True
    assert len(n["sources"]) == 4
    fres, lamb, raw = (n["vs_truth"][b] for b in ("diffuse-fresnel", "lambertian", "none"))
    # the issue's bounds: 3 % median, 10 % 95th percentile on visible nodes with sin β ≥ 0.3
    assert fres["nodes"] > 1500
    assert fres["median_abs_pct"] < 3.0 and fres["p95_abs_pct"] < 10.0
    # the paper's Lambertian model misses the Fresnel roll-off; raw misses the orientation
    assert lamb["p95_abs_pct"] > 12.0
    assert raw["median_abs_pct"] > 15.0 and raw["median_signed_pct"] < -15.0
    masked = n["masked_total"]
    assert masked["facing_away"] > 1000 and masked["grazing"] > 500 and masked["saturated"] == 0
    assert sum(masked.values()) == sum(s["nodes"] for s in n["sources"])


def test_normalize_outputs_are_complete_and_consistent(trans_run):
    import meshio

    result, _ = trans_run
    run = result.run_dir
    n = json.loads((run / "normalize" / "report.json").read_text())
    entry = n["sources"][0]
    rows = list(csv.DictReader((run / entry["files"]["csv"]).open()))
    assert len(rows) == entry["nodes"]
    used = [r for r in rows if r["mask"] == "ok"]
    assert len(used) == entry["used"]
    assert all(float(r["sin_beta"]) >= 0.3 for r in used)
    assert all(r["i0_diffuse-fresnel"] == "" for r in rows if r["mask"] != "ok")
    mesh = meshio.read(run / n["vtu"])
    key = "i0_diffuse-fresnel_v000_src_00"
    vals = np.array([float(r["i0_diffuse-fresnel"] or "nan") for r in rows])
    assert np.allclose(mesh.point_data[key], vals, equal_nan=True, rtol=1e-5)
    flat = cv2.imread(str(run / entry["files"]["flattened"]), cv2.IMREAD_UNCHANGED)
    assert flat.dtype == np.float32 and np.isfinite(flat).sum() > 1000
    assert (run / entry["files"]["preview"]).stat().st_size > 10_000
    paa = (run / entry["files"]["nirfast"]).read_text().splitlines()
    assert paa[0].split() == ["source", "det", "active", "amplitude", "phase"]
    det = [line.split() for line in paa[1:]]
    assert [d[:2] for d in det] == [["1", "1"], ["1", "2"]]
    # detector 1 faces the camera at view 0, detector 2 is on the far side
    assert det[0][2] == "1" and float(det[0][3]) > 0 and det[1][2] == "0"


def test_normalize_command_reruns_with_another_normalizer(trans_run, capsys):
    from dotshell.cli.app import main

    result, _ = trans_run
    assert main(["normalize", str(result.run_dir), "--normalizer", "lambertian",
                 "--min-sin-beta", "0.5"]) == 0
    out = "".join(capsys.readouterr().out.split())  # rich wraps at the test's 80 columns
    assert "normalizedwithlambertian" in out and "NormalizedI0vstrueI0" in out
    n = json.loads((result.run_dir / "report.json").read_text())["normalize"]
    assert n["normalizer"] == "lambertian" and n["min_sin_beta"] == 0.5
    assert min(s["sin_beta_used"]["min"] for s in n["sources"]) >= 0.5


def _copy_run(trans_run, tmp_path):
    src = trans_run[0].run_dir
    dst = tmp_path / src.name
    shutil.copytree(src, dst, symlinks=True)
    return dst


def test_truth_comes_from_the_run_directory_not_from_a_rig(trans_run, tmp_path, capsys,
                                                         monkeypatch):
    """The scan records the simulator's true light (truth.json); normalizing a copy of the run
    elsewhere, with building a rig made impossible, scores exactly as the scan did. Without
    truth.json the run is normalized and says it was not scored."""
    from dotshell.cli.app import main
    from dotshell.rig import assembly

    result, _ = trans_run
    index = json.loads((result.run_dir / "truth.json").read_text())
    views = index["transillumination"]["views"]
    assert {v: e["sources"] for v, e in views.items()} == {"0": ["src_00", "src_01"],
                                                           "3": ["src_00", "src_01"]}
    with np.load(result.run_dir / views["3"]["file"]) as data:
        assert len(data["vertices_mm"]) > 1000 and np.isfinite(data["radiance_src_01"]).all()

    def no_rig(*args, **kwargs):
        raise AssertionError("normalize built a Rig")

    monkeypatch.setattr(assembly.Rig, "__init__", no_rig)
    run = _copy_run(trans_run, tmp_path / "copy")
    assert main(["normalize", str(run)]) == 0
    n = json.loads((run / "report.json").read_text())["normalize"]
    assert n["vs_truth"] == result.report["normalize"]["vs_truth"]
    assert n["vs_truth"]["diffuse-fresnel"]["nodes"] > 1500
    capsys.readouterr()
    run = _copy_run(trans_run, tmp_path / "bare")
    (run / "truth.json").unlink()
    assert main(["normalize", str(run)]) == 0
    err = "".join(capsys.readouterr().err.split())  # rich wraps at the test's 80 columns
    assert "hasnotruth.json" in err and "notscoredagainstthetruth" in err
    n = json.loads((run / "report.json").read_text())["normalize"]
    assert "vs_truth" not in n and n["sources"][0]["used"] > 0


def test_unscanned_nodes_are_found_a_chunk_of_the_cloud_at_a_time(trans_run):
    """Issue 33: the nodes with no cloud point near them are found by searching the mapped
    cloud a chunk at a time (the agar's 8.3 M points as float64 and their k-d tree were the
    scan's peak after the capture): the same nodes as one search of the whole cloud, whatever
    the chunk, and the closed bottom among them."""
    from scipy.spatial import cKDTree

    from dotshell.fem.meshfiles import read_surface
    from dotshell.pipeline.normalize import unscanned_nodes
    from dotshell.run.ply import read_ply
    from dotshell.run.store import RunStore

    result, _ = trans_run
    store = RunStore.open(result.run_dir)
    surface = read_surface(store.path("surface.ply"))
    points, _ = read_ply(store.path("cloud.ply"))
    dist, _ = cKDTree(points).query(surface.vertices, distance_upper_bound=0.5)
    whole = ~np.isfinite(dist)
    assert 0 < whole.sum() < len(whole)  # the mesher's closed bottom, and the scanned side
    bottom = surface.vertices[:, 2] < 0.1
    assert whole[bottom].mean() > 0.9
    for chunk in (997, 1 << 20):
        assert np.array_equal(unscanned_nodes(store, surface, 0.5, chunk=chunk), whole)


def test_bad_runs_are_clear_errors(trans_run, small_scan, tmp_path, capsys):
    from dotshell.cli.app import main

    assert main(["normalize", str(small_scan[0].run_dir)]) == 2
    assert "has no trans-illumination frames" in capsys.readouterr().err
    run = _copy_run(trans_run, tmp_path)
    (run / "current" / "surface.ply").unlink()  # a damaged generation
    assert main(["normalize", str(run)]) == 2
    err = capsys.readouterr().err
    assert "has no surface" in err and "dotshell mesh" in err
    run = _copy_run(trans_run, tmp_path / "b")
    (run / "current" / "calibration.json").unlink()
    assert main(["normalize", str(run)]) == 2
    assert "has no calibration.json" in capsys.readouterr().err
    run = _copy_run(trans_run, tmp_path / "c")
    frame = run / "transillumination" / "view_003" / "src_01.png"
    cv2.imwrite(str(frame), np.zeros((10, 12), np.uint16))
    assert main(["normalize", str(run)]) == 2
    err = capsys.readouterr().err
    assert "src_01.png is 12x10 px" in err and "Traceback" not in err


def test_saturated_frames_are_named_and_their_nodes_masked(tmp_path):
    from conftest import write_profile

    from dotshell.events import EventBus, Message
    from dotshell.pipeline.scan import scan
    from dotshell.plugins import PluginManager
    from dotshell.profile.loader import load_profile

    raw = transillumination_profile(exposure_ms=40.0, views=[0], targets_mm=[[0.0, 10.0]])
    raw["scan"]["views"] = 4
    # a 2 mm mesh (a quarter of the nodes, a third of the scan's time) and no previews: the
    # saturation is in the frames, the nodes only have to map onto them
    raw["mesh"]["node_distance_mm"] = 2.0
    raw["outputs"] = {"previews": False}
    pm = PluginManager()
    pm.load_entry_points()
    warnings = []
    bus = EventBus()
    bus.subscribe(lambda ev: warnings.append(ev.text) if isinstance(ev, Message) else None)
    result = scan(load_profile(write_profile(tmp_path / "p.toml", raw), pm), pm,
                  tmp_path / "runs", bus=bus)
    n = result.report["normalize"]
    assert n["masked_total"]["saturated"] > 50  # measured 122 of 523 nodes (470 at 1 mm)
    assert any("view_000/src_00.png" in w and "saturated pixels" in w for w in warnings)


def test_a_view_is_reconstructed_before_its_trans_illumination_is_captured(tmp_path,
                                                                           monkeypatch):
    """Issue 33: a trans-illumination view's light (the simulated laser's view, ~0.12 GB at full
    resolution) is not made beside a view's reconstruction (~0.15 GB): together they were the
    agar scan's peak memory. Each reconstruction here waits until the scan waits for it, so a
    scan that captured the trans-illumination without waiting would find it unfinished."""
    import threading

    from conftest import write_profile

    from dotshell.events import EventBus
    from dotshell.pipeline import scan as scan_module
    from dotshell.pipeline.transillum import TransilluminationCapture
    from dotshell.plugins import PluginManager
    from dotshell.profile.loader import load_profile

    raw = transillumination_profile(views=[0, 1])
    raw["scan"]["views"] = 3
    raw["mesh"]["after_scan"] = False
    raw["outputs"] = {"previews": False}
    gates: dict[int, threading.Event] = {}
    pipelines: list = []
    seen: dict[int, bool] = {}
    real_wait, real_reconstruct = scan_module.ViewPipeline._wait, \
        scan_module.ViewPipeline._reconstruct
    real_submit, real_trans = scan_module.ViewPipeline.submit, TransilluminationCapture.run_view

    def gate(view: int) -> threading.Event:
        return gates.setdefault(view, threading.Event())

    def submit(self, view, angle_deg, images):
        pipelines.append(self)
        return real_submit(self, view, angle_deg, images)

    def wait(self, keep_pending):  # whoever waits for the reconstructions lets them run
        for view in list(self.futures):
            gate(view).set()
        return real_wait(self, keep_pending)

    def reconstruct(self, view, angle_deg, images):
        assert gate(view).wait(600), "nobody waited for the reconstruction"
        return real_reconstruct(self, view, angle_deg, images)

    def trans(self, view):
        seen[view] = pipelines[-1].futures[view].done()
        return real_trans(self, view)

    monkeypatch.setattr(scan_module.ViewPipeline, "submit", submit)
    monkeypatch.setattr(scan_module.ViewPipeline, "_wait", wait)
    monkeypatch.setattr(scan_module.ViewPipeline, "_reconstruct", reconstruct)
    monkeypatch.setattr(TransilluminationCapture, "run_view", trans)
    pm = PluginManager()
    pm.load_entry_points()
    result = scan_module.scan(load_profile(write_profile(tmp_path / "p.toml", raw), pm), pm,
                              tmp_path / "runs", bus=EventBus())
    assert json.loads((result.run_dir / "manifest.json").read_text())["status"] == "completed"
    assert seen == {0: True, 1: True}
