"""Tests of the simulated rig (plugins/dotshell_sim) on the reference bench scaled to 1/4."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from dotshell.backends import RigContext
from dotshell.errors import DeviceError, ProfileError
from dotshell.geometry.lens import lens_from_fov
from dotshell_sim.bench import build_rig, scale_profile

PROFILE = Path(__file__).resolve().parents[1] / "profiles" / "sim-metal-cylinder.toml"
FACTOR = 0.25
CYL, PLATE, BACKGROUND = 0, 1, 2  # material ids of the reference scene


def load_profile() -> dict:
    with open(PROFILE, "rb") as f:
        return tomllib.load(f)


def make_rig(factor=FACTOR, **camera_overrides):
    prof = scale_profile(load_profile(), factor)
    prof["camera"]["settings"].update(camera_overrides)
    rig = build_rig(prof, RigContext())
    for dev in rig.values():
        dev.connect()
    rig["camera"].set_exposure(prof["scan"]["exposure_ms"])
    return rig


def full(value, projector):
    w, h = projector.resolution
    return np.full((h, w), value, np.uint8)


@pytest.fixture(scope="module")
def rig():
    return make_rig()


@pytest.fixture(scope="module")
def frames(rig):
    """White and black frames at 0° plus the view's geometry."""
    cam, proj, stage = rig["camera"], rig["projector"], rig["stage"]
    stage.move_to(0.0)
    proj.show(full(255, proj))
    white = cam.capture()
    proj.show(full(0, proj))
    black = cam.capture()
    view = cam.world.renderer().view(0.0)
    return white, black, view


def test_profile_sections_validate_and_scale():
    prof = load_profile()
    assert prof["camera"]["backend"] == "sim-camera"
    rig = build_rig(prof)  # factories validate settings (unknown keys would raise)
    cal = rig["camera"].ground_truth_calibration()
    small = build_rig(scale_profile(prof, FACTOR))["camera"].ground_truth_calibration()
    expect = cal.camera.scaled(FACTOR)
    assert small.camera.size == expect.size == (320, 256)
    np.testing.assert_allclose(small.camera.K, expect.K, atol=1e-12)
    np.testing.assert_allclose(small.projector.K, cal.projector.scaled(FACTOR).K, atol=1e-12)
    np.testing.assert_allclose(small.R, cal.R)
    # the bench: ~22.7° triangulation angle at the point the optical axes cross
    c_p = cal.projector_centre
    cross = np.array([0.0, 0.0, 200.0])
    a, b = -cross, c_p - cross
    angle = np.degrees(np.arccos(a @ b / np.linalg.norm(a) / np.linalg.norm(b)))
    assert 20 < angle < 25
    assert cal.source == "ground-truth"


def test_bad_setting_is_a_profile_error():
    from dotshell_sim.devices import make_camera

    with pytest.raises(ProfileError):
        make_camera(settings={"bit_depth": 10}, context=RigContext())


def test_white_frame_bright_on_cylinder_dark_on_background(frames, rig):
    white, black, view = frames
    assert white.dtype == np.uint16 and white.max() <= 4095
    cyl = view.material_fraction(CYL) == 1
    bg = view.material_fraction(BACKGROUND) == 1
    assert cyl.sum() > 5000 and bg.sum() > 5000
    assert np.median(white[cyl]) > 1500          # bright ...
    assert np.mean(white[cyl] >= 4095) < 0.10    # ... but mostly unsaturated
    assert np.median(white[bg]) < 40             # dark background (albedo 0.03)
    assert np.median(black[cyl]) < 60            # projector black + ambient only


def test_cast_shadow_on_plate(frames):
    white, black, view = frames
    plate = view.material_fraction(PLATE) == 1
    shadow = view.shadow_fraction() == 1
    shadow_px = plate & shadow
    lit_px = plate & (view.lit_fraction() == 1)
    assert shadow_px.sum() > 200 and lit_px.sum() > 200
    lit, dark = np.median(white[lit_px]), np.median(white[shadow_px])
    assert lit > 300
    assert dark < 0.1 * lit
    # in the shadow the white frame looks like the black frame (ambient only)
    assert abs(float(np.median(white[shadow_px])) - float(np.median(black[shadow_px]))) < 10


def test_geometry_triangulates_back_onto_the_cylinder(rig):
    """Projector coordinates of traced hits + the ground-truth calibration → points on the
    cylinder (exact geometry, far below 1 µm)."""
    cam = rig["camera"]
    cal = cam.ground_truth_calibration()
    renderer = cam.world.renderer()
    rng = np.random.default_rng(3)
    w, h = cam.resolution
    pix = np.column_stack([rng.uniform(-0.5, w - 0.5, 4000), rng.uniform(-0.5, h - 0.5, 4000)])
    for angle in (0.0, 47.0):
        tr = renderer.trace(pix, angle)
        z = cal.camera_to_sample(np.nan_to_num(tr.points), angle)[:, 2]
        side = (tr.material == CYL) & tr.lit & (z < 29.999)
        assert side.sum() > 500
        np.testing.assert_allclose(
            tr.projector[side], cal.projector.project(tr.points[side] @ cal.R.T + cal.T),
            atol=1e-9)
        # camera ray ∩ plane through the projector centre containing projector column u
        u, v = tr.projector[side].T
        r1 = cal.projector.rays(np.column_stack([u, v - 0.5]))
        r2 = cal.projector.rays(np.column_stack([u, v + 0.5]))
        normal = np.cross(r1, r2) @ cal.R
        d = cal.camera.rays(pix[side])
        t = (normal @ cal.projector_centre) / np.einsum("ij,ij->i", normal, d)
        s = cal.camera_to_sample(t[:, None] * d, angle)
        assert np.abs(np.hypot(s[:, 0], s[:, 1]) - 7.7).max() < 1e-3 * 1e-3  # < 1 µm
        assert s[:, 2].min() > 0 and s[:, 2].max() < 30


def _crossing(profile: np.ndarray, near: float) -> float:
    """Sub-pixel position where a 1-D profile crosses 0.5 (linear interpolation), nearest
    ``near``."""
    j = np.flatnonzero(np.diff(np.sign(profile - 0.5)) != 0)
    j = j[np.argmin(np.abs(j - near))]
    return j + (0.5 - profile[j]) / (profile[j + 1] - profile[j])


def test_stripe_edge_lands_where_geometry_says():
    """A vertical black/white edge between projector columns c-1 and c (at x = c - 0.5)
    renders where the ray tracer puts it: (1) the rendered row equals an independent
    evaluation (trace each sub-pixel ray, bilinear edge, area average) and (2) its 50 % crossing
    is at the traced camera column within the error of a linear-interpolation edge estimator
    (no half-pixel convention slips)."""
    prof = scale_profile(load_profile(), FACTOR)
    prof["camera"]["settings"]["defocus_sigma_px"] = 0.0
    prof["projector"]["settings"]["defocus_sigma_px"] = 0.0
    prof["projector"]["settings"]["black_level"] = 0.0
    rig = build_rig(prof, RigContext())
    for d in rig.values():
        d.connect()
    cam, proj = rig["camera"], rig["projector"]
    pw, ph = proj.resolution
    renderer = cam.world.renderer()
    ss = renderer.ss
    w = cam.resolution[0]
    row = 128
    proj.show(full(0, proj))
    black = cam.expected_electrons()[row]  # ambient light only
    proj.show(full(255, proj))
    white = cam.expected_electrons()[row] - black
    # independent evaluation: sub-pixel rays of this row
    sub = (np.arange(ss) + 0.5) / ss - 0.5
    px = (np.arange(w)[:, None, None] + sub[None, None, :]) + 0 * sub[None, :, None]
    py = row + sub[None, :, None] + 0 * px
    tr_sub = renderer.trace(np.column_stack([px.ravel(), py.ravel()]), 0.0)
    xs = np.arange(0.0, w - 1, 0.005)
    tr = renderer.trace(np.column_stack([xs, np.full_like(xs, row)]), 0.0)
    for c in (100, 120, 140, 160):
        edge = np.zeros((ph, pw), np.uint8)
        edge[:, :c] = 255
        proj.show(edge)
        img = cam.expected_electrons()[row] - black
        rendered = img / np.maximum(white, 1e-9)
        bilinear = np.clip(c - np.nan_to_num(tr_sub.projector[:, 0], nan=1e9), 0.0, 1.0)
        wsum = tr_sub.weight.reshape(w, -1).sum(axis=1)
        reference = (tr_sub.weight * bilinear).reshape(w, -1).sum(axis=1) / np.maximum(wsum, 1e-12)
        u = np.where((tr.material == CYL) & tr.lit, tr.projector[:, 0], np.nan)
        k = np.flatnonzero((u[:-1] - (c - 0.5)) * (u[1:] - (c - 0.5)) <= 0)
        assert k.size == 1
        x_true = xs[k[0]]
        x_rendered = _crossing(rendered, x_true)
        assert abs(x_rendered - _crossing(reference, x_true)) < 1e-3  # camera px
        assert abs(x_rendered - x_true) < 0.15


@pytest.mark.parametrize("bits,dtype,top", [(8, np.uint8, 255), (12, np.uint16, 4095)])
def test_frame_dtype_range_and_saturation(bits, dtype, top):
    rig = make_rig(bit_depth=bits, supersample=1)
    cam, proj = rig["camera"], rig["projector"]
    proj.show(full(255, proj))
    f = cam.capture()
    assert f.dtype == dtype and f.shape == (256, 320)
    assert cam.bit_depth == bits and cam.resolution == (320, 256)
    assert f.max() <= top and f.max() > top // 4
    cam.set_exposure(1000.0)
    assert cam.capture().max() == top  # clipped at full scale, no wrap-around


def test_noise_matches_shot_and_read_model():
    rig = make_rig(seed=11, defocus_sigma_px=0.0)
    cam, proj = rig["camera"], rig["projector"]
    proj.show(full(128, proj))
    mean_e = cam.expected_electrons()
    stack = np.stack([cam.capture().astype(np.float64) for _ in range(24)])
    model = cam.sensor
    flat = (mean_e > 500) & (mean_e < 0.8 * model.full_well_e)
    assert flat.sum() > 3000
    measured = stack.std(axis=0, ddof=1)[flat]
    expected = model.expected_std_dn(mean_e[flat])
    ratio = np.sqrt(np.mean(measured ** 2) / np.mean(expected ** 2))
    assert 0.95 < ratio < 1.05
    # the mean is right too (gain and offset)
    mean_dn = stack.mean(axis=0)[flat]
    pred = mean_e[flat] * model.gain_dn_per_e + model.dark_offset_dn
    assert np.abs(np.median(mean_dn - pred)) < 0.5
    # and read noise alone (a vanishing exposure collects no electrons)
    cam.set_exposure(1e-9)
    frames = np.stack([cam.capture().astype(float) for _ in range(8)])
    std = frames.std(axis=0, ddof=1).mean()
    assert abs(std - float(model.expected_std_dn(0.0))) < 0.3


def test_same_seed_reproduces_frames():
    a, b, c = make_rig(seed=5), make_rig(seed=5), make_rig(seed=6)
    for r in (a, b, c):
        r["projector"].show(full(200, r["projector"]))
    fa = [a["camera"].capture() for _ in range(2)]
    fb = [b["camera"].capture() for _ in range(2)]
    fc = c["camera"].capture()
    assert np.array_equal(fa[0], fb[0]) and np.array_equal(fa[1], fb[1])
    assert not np.array_equal(fa[0], fa[1])   # frame counter changes the noise
    assert not np.array_equal(fa[0], fc)


def test_device_errors():
    prof = scale_profile(load_profile(), FACTOR)
    rig = build_rig(prof, RigContext())
    cam, proj, stage = rig["camera"], rig["projector"], rig["stage"]
    with pytest.raises(DeviceError, match="connect"):
        cam.capture()
    with pytest.raises(DeviceError, match="connect"):
        stage.move_to(10)
    with pytest.raises(DeviceError, match="connect"):
        proj.show(full(0, proj))
    proj.connect()
    with pytest.raises(DeviceError, match="uint8"):
        proj.show(np.zeros((10, 10), np.uint8))
    # a camera alone in its world has nothing to look at
    from dotshell_sim.devices import make_camera

    lonely = make_camera(settings=prof["camera"]["settings"], context=RigContext())
    lonely.connect()
    with pytest.raises(DeviceError, match="sim-projector"):
        lonely.capture()
    with pytest.raises(DeviceError):
        lonely.ground_truth_calibration()
    with pytest.raises(DeviceError):
        lonely.set_exposure(-1)


def test_stage_analyzer_laser_state():
    from dotshell_sim.devices import make_analyzer, make_laser, make_turntable

    ctx = RigContext()
    stage = make_turntable(settings={"steps_per_degree": 10.0}, context=ctx)
    an = make_analyzer(settings={}, context=ctx)
    laser = make_laser(settings={}, context=ctx)
    for d in (stage, an, laser):
        d.connect()
    stage.move_to(12.345)
    assert stage.position == pytest.approx(12.3)
    assert stage.status()["angle_deg"] == pytest.approx(12.3)
    an.set_angle(90)
    laser.set(True)
    world = ctx.shared["dotshell_sim"]
    assert world.stage is stage and world.analyzer.angle_deg == 90 and world.laser.on
    laser.close()
    laser.close()  # safe twice
    assert not laser.on


def test_rotation_moves_an_off_axis_cylinder():
    prof = scale_profile(load_profile(), FACTOR / 2)
    prof["camera"]["settings"]["supersample"] = 1
    prof["stage"]["settings"]["scene"]["offset_mm"] = [4.0, 0.0]  # towards the camera at 0°
    rig = build_rig(prof, RigContext())
    for d in rig.values():
        d.connect()
    renderer = rig["camera"].world.renderer()
    cols = []
    for angle in (90.0, 270.0):
        mask = renderer.view(angle).material_fraction(CYL) > 0.5
        cols.append(np.nonzero(mask.any(axis=0))[0].mean())
    # stage x→y at +90°: the cylinder moves sideways; opposite ways at 90° and 270°
    assert abs(cols[0] - cols[1]) > 10


def test_hooks_provide_backends():
    import pluggy

    import dotshell.hookspecs
    import dotshell_sim

    pm = pluggy.PluginManager("dotshell")
    pm.add_hookspecs(dotshell.hookspecs)
    pm.register(dotshell_sim, name="sim")
    names = {b.name for hook in (pm.hook.dotshell_cameras, pm.hook.dotshell_projectors,
                                 pm.hook.dotshell_stages, pm.hook.dotshell_analyzers,
                                 pm.hook.dotshell_light_sources)
             for backends in hook() for b in backends}
    assert names == {"sim-camera", "sim-camera-faulty", "sim-projector", "sim-turntable",
                     "sim-analyzer", "sim-laser"}
    camera, _faulty = pm.hook.dotshell_cameras()[0]
    assert camera.settings_schema["bit_depth"].default == 12


def test_fast_projection_matches_lens_project():
    from dotshell_sim.render import project_points

    lens = lens_from_fov(640, 480, 1500.0, (-0.1, 0.05, 0.001, -0.002, 0.01), 330.0, 230.0)
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-40, 40, 500), rng.uniform(-30, 30, 500),
                           rng.uniform(150, 250, 500)])
    uv, ok = project_points(lens, pts)
    assert ok.all()
    np.testing.assert_allclose(uv, lens.project(pts), atol=1e-9)


def _reference_noise_e(lam: np.ndarray, model, rng) -> np.ndarray:
    """Shot + read noise drawn the exact way: Poisson, full-well clip, normal read noise."""
    e = np.minimum(rng.poisson(lam).astype(np.float64), model.full_well_e)
    return e + model.read_noise_e * rng.standard_normal(lam.shape)


@pytest.mark.parametrize("lam_e, read_noise_e", [(200.0, 10.0), (4.7, 10.0), (60.0, 10.0),
                                                 (3.0, 0.0), (9990.0, 10.0)])
def test_sensor_noise_distribution_matches_exact_draw(lam_e, read_noise_e):
    """The sensor's draw (normal where shot + read noise is nearly symmetric, exact Poisson
    elsewhere) has the distribution of the exact draw: its CDF in DN differs by < 0.5 % (the
    normal's worst case is at λ = 2 r², 200 e- for 10 e- of read noise), mean and std agree."""
    from dotshell_sim.render import SensorModel, sensor

    model = SensorModel(12, 10000.0, read_noise_e, 4095 / 10000.0 if read_noise_e else 1.0, 8.0)
    lam = np.full((400, 500), lam_e, np.float32)
    got = sensor(lam, model, np.random.default_rng(3)).astype(np.float64).ravel()
    e = _reference_noise_e(lam.astype(np.float64), model, np.random.default_rng(4))
    ref = np.clip(np.rint(e * model.gain_dn_per_e + model.dark_offset_dn), 0, model.max_dn).ravel()
    grid = np.arange(model.max_dn + 1)
    cdf_got = np.searchsorted(np.sort(got), grid, side="right") / got.size
    cdf_ref = np.searchsorted(np.sort(ref), grid, side="right") / ref.size
    assert np.abs(cdf_got - cdf_ref).max() < 0.005
    assert abs(got.mean() - ref.mean()) < 0.02 * max(1.0, ref.std())
    assert got.std() == pytest.approx(ref.std(), rel=0.02)
    if read_noise_e == 0:  # no read noise: whole electrons, exact Poisson (P(0) = e^-3)
        assert np.all(got == np.rint(got))
        assert (got == model.dark_offset_dn).mean() == pytest.approx(np.exp(-lam_e), abs=0.005)


def test_exact_poisson_range_brackets_the_skewed_means():
    """The means drawn exactly are those whose shot + read noise skewness passes the bound."""
    from dotshell_sim.render import NORMAL_SKEW_MAX, exact_poisson_range

    assert exact_poisson_range(10.0) == (0.0, 0.0)  # peak skewness 0.038 < 0.05
    lo, hi = exact_poisson_range(0.0)
    assert lo == 0.0 and hi == pytest.approx(1 / NORMAL_SKEW_MAX ** 2)
    lo, hi = exact_poisson_range(5.0)
    for lam, inside in ((lo * 0.99, False), (lo * 1.01, True), (hi * 0.99, True),
                        (hi * 1.01, False)):
        assert (lam / (lam + 25.0) ** 1.5 > NORMAL_SKEW_MAX) == inside


def test_symmetric_sample_shares_one_view_across_angles():
    """A cylinder on the turntable axis looks the same at every stage angle: the renderer makes
    its view once and the view of another angle is the same to float32 rounding (compared with
    that angle traced afresh); an off-axis cylinder gets a view of its own per angle."""
    from dotshell_sim.render import Renderer

    rig = make_rig()
    renderer = rig["camera"].world.renderer()
    assert renderer.scene.turns_into_itself()
    v0 = renderer.view(0.0)
    v1 = renderer.view(137.0)
    assert v1.map_x is v0.map_x and v1.angle_deg == 137.0
    fresh = Renderer(renderer.calib, renderer.scene, renderer.ss, renderer.ambient,
                     renderer.projector_ref_mm).view(137.0)
    lit = fresh.weight > 0
    assert np.array_equal(lit, v1.weight > 0)
    assert np.mean(fresh.material != v1.material) < 1e-4
    for a, b in ((fresh.map_x, v1.map_x), (fresh.map_y, v1.map_y)):
        assert np.abs(a[lit] - b[lit]).max() < 1e-3  # projector pixels
    assert np.allclose(fresh.weight, v1.weight, rtol=1e-5, atol=1e-7)

    prof = scale_profile(load_profile(), FACTOR)
    prof["stage"]["settings"]["scene"]["offset_mm"] = [2.0, 0.0]
    off = build_rig(prof, RigContext())
    for dev in off.values():
        dev.connect()
    off_renderer = off["camera"].world.renderer()
    assert not off_renderer.scene.turns_into_itself()
    w0 = off_renderer.view(0.0)
    assert off_renderer.view(137.0).map_x is not w0.map_x


def test_renderer_drops_its_large_view_before_making_the_next(monkeypatch):
    """Issue 33: a renderer keeping ``cache_views`` = 1 large view forgets it before it traces
    the next angle's (at full resolution each is ~0.1 GB; a scan never turns back), so two
    views are never held at once, and its camera rays once the view is made (made again the
    same); small views (below SMALL_VIEWS_BYTES) stay cached."""
    import dotshell_sim.render as render

    prof = scale_profile(load_profile(), FACTOR)
    prof["stage"]["settings"]["scene"]["offset_mm"] = [2.0, 0.0]  # a view per angle
    rig = build_rig(prof, RigContext())
    for dev in rig.values():
        dev.connect()
    renderer = rig["camera"].world.renderer()
    renderer.release()  # renderers are shared by geometry: start from none cached
    renderer.view(0.0)
    held_while_tracing: list[int] = []
    trace = renderer.trace

    def counting_trace(*args, **kwargs):
        held_while_tracing.append(len(renderer._views))
        return trace(*args, **kwargs)

    monkeypatch.setattr(renderer, "trace", counting_trace)
    renderer.view(20.0)  # small views: kept
    assert held_while_tracing and set(held_while_tracing) == {1}
    assert list(renderer._views) == [0.0, 20.0]
    monkeypatch.setattr(render, "SMALL_VIEWS_BYTES", 0)  # every view counts as large
    held_while_tracing.clear()
    renderer.view(40.0)
    assert held_while_tracing and set(held_while_tracing) == {0}
    assert list(renderer._views) == [40.0]
    assert renderer._rays is None  # large: made again for the next view
    rays = renderer.camera_rays().copy()
    renderer.forget_large_rays()
    assert np.array_equal(renderer.camera_rays(), rays)
