"""The merge step (`dotshell.pipeline.steps.cloud_step`) reads each view's points into the
merged PLY's bytes, which the later steps read as the cloud (issue 33: no list of parts, no
concatenated copy, no bytes copy): the same file, bit for bit, as writing the concatenation."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from dotshell.pipeline.steps import cloud_step
from dotshell.run.layout import RunLayout
from dotshell.run.ply import read_ply, write_ply


def test_the_merged_cloud_is_the_file_s_bytes_and_the_file_is_the_concatenation(tmp_path):
    rng = np.random.default_rng(5)
    parts = {0: rng.normal(size=(300, 3)), 2: rng.normal(size=(0, 3)),
             3: rng.normal(size=(450, 3)) * 20.0}
    (tmp_path / RunLayout.VIEWS).mkdir()
    for view, pts in parts.items():
        write_ply(tmp_path / RunLayout.view_cloud(view), pts)
    ctx = SimpleNamespace(store=SimpleNamespace(path=lambda rel: tmp_path / rel),
                          bus=SimpleNamespace(emit=lambda ev: None), options={}, timings={},
                          cloud=None)
    assert cloud_step(ctx) == {"cloud": {"path": RunLayout.CLOUD, "points": 750}}

    stored = [read_ply(tmp_path / RunLayout.view_cloud(v), float_type=np.float32)[0]
              for v in parts]
    ids = np.repeat(np.array(list(parts), np.float32), [len(p) for p in stored])
    write_ply(tmp_path / "expected.ply", np.concatenate(stored), view=ids)
    assert (tmp_path / RunLayout.CLOUD).read_bytes() == (tmp_path / "expected.ply").read_bytes()
    assert ctx.cloud.dtype == np.float32 and ctx.cloud.shape == (750, 3)
    assert np.array_equal(ctx.cloud, np.concatenate(stored))
    assert ctx.cloud.base is not None  # a view of the file's bytes, not a copy of its own


def test_the_cloud_preview_draws_the_same_points_and_colours_picked_first(tmp_path, monkeypatch):
    """The cloud preview picks the points it draws before it takes the colour scale over all
    of them in place (one cloud-sized float64 array, not two; issue 33): the same points,
    colours and scale as picking after."""
    from dotshell.render import previews

    drawn = []
    monkeypatch.setattr(previews, "PREVIEW_POINTS", 500)
    monkeypatch.setattr(previews, "cloud_preview", lambda points, scalars, path, title, name,
                        **style: drawn.append((points, scalars, style)) or path)
    rng = np.random.default_rng(2)
    theta = rng.uniform(0, 2 * np.pi, 4000)
    r = 12.92 + rng.normal(0, 0.02, 4000)
    points = np.column_stack([r * np.cos(theta), r * np.sin(theta),
                              rng.uniform(0, 30, 4000)]).astype(np.float32)
    profile = SimpleNamespace(name="p", validation=SimpleNamespace(shape="cylinder",
                                                                   radius_mm=12.92))
    store = SimpleNamespace(path=lambda rel: tmp_path / rel, root=tmp_path)
    previews.cloud_previews(store, points, profile, bus=None)
    [(got_points, got_scalars, style)] = drawn
    error = np.hypot(points[:, 0], points[:, 1], dtype=np.float64) - 12.92
    pick = np.random.default_rng(0).choice(4000, 500, replace=False)
    assert np.array_equal(got_points, points[pick]) and np.array_equal(got_scalars, error[pick])
    cap = max(0.01, 4 * float(np.median(np.abs(error))))
    assert style == {"clim": (-cap, cap), "cmap": "coolwarm"}


def test_the_mesh_step_lets_the_in_memory_cloud_go(monkeypatch):
    """The mesh process reads cloud.ply and no later step reads the cloud in this process: the
    merge's in-memory cloud is let go when the mesh step starts (issue 33)."""
    import dotshell.pipeline.mesh as mesh
    from dotshell.pipeline.steps import mesh_step

    held = []
    ctx = SimpleNamespace(store=None, profile=None, pm=None, bus=None, options={}, _calib=None,
                          cloud=np.zeros((10, 3), np.float32))
    monkeypatch.setattr(mesh, "mesh_stage", lambda *args: held.append(ctx.cloud) or {})
    assert mesh_step(ctx) == {"mesh": {}} and held == [None]
