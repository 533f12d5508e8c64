"""The merge step (`dotshell.pipeline.steps.cloud_step`) copies each view's mapped points into
the merged PLY's bytes, which the later steps read as the cloud (issue 33: no list of parts, no
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
