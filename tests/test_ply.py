"""PLY clouds made elsewhere: open3d's (double, ASCII, colours), big-endian and ASCII files with
other elements, read like dotshell's own; an open3d PLY as `reconstruct --reference` gives the
same comparison as the MATLAB reference it was made from. Speed: benchmarks/ply_read.py."""

from __future__ import annotations

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from dotshell.cli.app import main
from dotshell.runtime.compat import import_open3d
from dotshell.errors import RunError
from dotshell.run.ply import read_ply, write_ply
from test_captures import SKULL, needs_skull


def _cloud(n: int = 500, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(scale=20.0, size=(n, 3)) + [0.0, 0.0, 200.0]


@pytest.mark.parametrize("ascii", [True, False])
def test_open3d_double_and_coloured_ply_reads_as_written(tmp_path, ascii):
    o3d = import_open3d()
    pts = _cloud()
    colours = np.random.default_rng(1).uniform(size=pts.shape)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.colors = o3d.utility.Vector3dVector(colours)
    path = tmp_path / "o3d.ply"
    assert o3d.io.write_point_cloud(str(path), pcd, write_ascii=ascii)
    header = path.read_bytes()[:400]
    assert b"property double x" in header and (b"format ascii" in header) == ascii
    got, scalars = read_ply(path)
    assert np.array_equal(got, np.asarray(o3d.io.read_point_cloud(str(path)).points))
    assert np.allclose(got, pts, rtol=5e-6 if ascii else 1e-15, atol=0)  # ASCII: 6 digits
    assert set(scalars) == {"red", "green", "blue"}
    assert np.abs(scalars["red"] - np.round(colours[:, 0] * 255)).max() <= 1


def test_big_endian_float_with_faces_and_ascii_float(tmp_path):
    pts = _cloud(50).astype(np.float32)
    vertex = np.empty(len(pts), [("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("quality", ">f8")])
    for i, a in enumerate("xyz"):
        vertex[a] = pts[:, i]
    vertex["quality"] = np.arange(len(pts))
    faces = np.empty(2, [("vertex_indices", "O")])
    faces["vertex_indices"] = [np.array([0, 1, 2], "i4"), np.array([1, 2, 3], "i4")]
    for text, name in ((False, "be.ply"), (True, "a.ply")):
        PlyData([PlyElement.describe(vertex, "vertex"), PlyElement.describe(faces, "face")],
                text=text, byte_order=">").write(str(tmp_path / name))
        got, scalars = read_ply(tmp_path / name, float_type=np.float32)
        assert got.dtype == np.float32 and np.array_equal(got, pts)
        assert np.array_equal(scalars["quality"], np.arange(len(pts)))


def test_own_ply_round_trip_and_refusals(tmp_path):
    pts = _cloud(100)
    write_ply(tmp_path / "c.ply", pts, view=np.arange(100) % 3)
    got, scalars = read_ply(tmp_path / "c.ply")
    assert np.allclose(got, pts.astype(np.float32)) and set(scalars) == {"view"}
    path = tmp_path / "cut.ply"
    path.write_bytes((tmp_path / "c.ply").read_bytes()[:-8])
    with pytest.raises(RunError, match="cut.ply is not a point cloud dotshell can read"):
        read_ply(path)
    nan = pts.copy()
    nan[3] = np.nan
    write_ply(tmp_path / "nan.ply", nan)
    with pytest.raises(RunError, match="1 of its 100 points have non-finite"):
        read_ply(tmp_path / "nan.ply")
    assert len(read_ply(tmp_path / "nan.ply", finite=False)[0]) == 100
    no_xyz = np.zeros(3, [("a", "<f4")])
    PlyData([PlyElement.describe(no_xyz, "vertex")]).write(str(tmp_path / "a.ply"))
    with pytest.raises(RunError, match="need x, y, z"):
        read_ply(tmp_path / "a.ply")


def test_point_chunks_read_the_cloud_a_chunk_at_a_time(tmp_path):
    """point_chunks (the normalization's pass over the cloud, issue 33): the points read_ply
    reads, as float64 chunks, from dotshell's binary files (read, not mapped), big-endian
    doubles with another element before them, and ASCII; a non-finite point is refused
    naming the file, as read_ply does."""
    from dotshell.run.ply import point_chunks

    pts = _cloud(2503)
    own = write_ply(tmp_path / "c.ply", pts, view=np.arange(len(pts)) % 3)
    vertex = np.empty(len(pts), [("quality", ">f8"), ("x", ">f8"), ("y", ">f8"), ("z", ">f8")])
    for i, a in enumerate("xyz"):
        vertex[a] = pts[:, i]
    vertex["quality"] = 1.0
    faces = np.empty(1, [("vertex_indices", "O")])
    faces["vertex_indices"] = [np.array([0, 1, 2], "i4")]
    for text, name in ((False, "be.ply"), (True, "a.ply")):
        PlyData([PlyElement.describe(faces, "face"), PlyElement.describe(vertex, "vertex")],
                text=text, byte_order=">").write(str(tmp_path / name))
    for path in (own, tmp_path / "be.ply", tmp_path / "a.ply"):
        chunks = list(point_chunks(path, chunk=1000))
        assert [len(c) for c in chunks] == [1000, 1000, 503]
        assert all(c.dtype == np.float64 for c in chunks)
        assert np.array_equal(np.vstack(chunks), read_ply(path)[0]), path.name
    nan = pts.copy()
    nan[[5, 2100]] = np.nan
    write_ply(tmp_path / "nan.ply", nan)
    with pytest.raises(RunError, match=r"nan\.ply .*2 of its 2503 points have non-finite"):
        list(point_chunks(tmp_path / "nan.ply", chunk=1000))


@needs_skull
def test_open3d_ascii_double_reference_works_as_reconstruct_reference(tmp_path, capsys):
    """SLStudio's skull cloud (pointCloud.mat) written by open3d as an ASCII PLY of doubles:
    `dotshell reconstruct --reference` compares against it as against the .mat (93876
    reference points, medians within 0.3 mm both ways, like test_captures' check)."""
    import json

    from dotshell.geometry.cloud_compare import load_reference_cloud

    o3d = import_open3d()
    ref = load_reference_cloud(SKULL / "skull_gray" / "pointCloud.mat")
    path = tmp_path / "skull-open3d.ply"
    o3d.io.write_point_cloud(str(path), o3d.geometry.PointCloud(
        o3d.utility.Vector3dVector(ref)), write_ascii=True)
    assert b"format ascii" in path.read_bytes()[:200]
    code = main(["reconstruct", "--captures", str(SKULL / "skull_gray"), "--calibration",
                 str(SKULL / "calibration.xml"), "--layout", "slstudio-graycode",
                 "--reference", str(path), "--out", str(tmp_path / "out")])
    assert code == 0, capsys.readouterr().err
    report = json.loads(next((tmp_path / "out").rglob("report.json")).read_text())
    got = report["reference"]
    assert got["reference_points"] == 93876
    assert got["to_reference_plane"]["median_mm"] <= 0.3
    assert got["reference_to_points"]["median_mm"] <= 0.3


def test_write_ply_writes_its_buffer_without_a_bytes_copy(tmp_path, monkeypatch):
    """The file's bytes are built once and written from there: no ``bytes`` copy of them (the
    merge's largest temporary, 133 MB on the agar scan's 8.3 M points; issue 33)."""
    import dotshell.run.ply as ply

    handed: list[object] = []
    write = ply.atomic_write_bytes

    def recording(path, data):
        handed.append(data)
        write(path, data)

    monkeypatch.setattr(ply, "atomic_write_bytes", recording)
    pts = _cloud(1000)
    write_ply(tmp_path / "c.ply", pts, view=np.arange(1000) % 4)
    assert len(handed) == 1 and not isinstance(handed[0], bytes)
    assert memoryview(handed[0]).nbytes == (tmp_path / "c.ply").stat().st_size
    got, scalars = read_ply(tmp_path / "c.ply", float_type=np.float32)
    assert np.array_equal(got, pts.astype(np.float32))
    assert np.array_equal(scalars["view"], np.arange(1000) % 4)
