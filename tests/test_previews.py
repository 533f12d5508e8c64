"""The 3-D previews (cloud, surface, volume) drawn by dotshell.render.raster: what is in the
picture (silhouettes, colours, the nearest point in front), and that no OpenGL renderer is
loaded for them (pyvista's plotting cost 1-2 s of CPU in every reconstruct and mesh, issue 32)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

from dotshell.fem.meshes import TetMesh, TriangleSurface
from dotshell.fem.meshfiles import read_surface, read_volume, write_surface, write_volume
import dotshell.render.raster as raster
from dotshell.render.mesh_previews import render_mesh_previews
from dotshell.render.previews import cloud_preview

ROOT = Path(__file__).resolve().parents[1]


def _cylinder(n: int = 200_000, radius: float = 10.0, height: float = 30.0, seed: int = 0):
    rng = np.random.default_rng(seed)
    a = rng.uniform(0, 2 * np.pi, n)
    return np.column_stack([radius * np.cos(a), radius * np.sin(a), rng.uniform(0, height, n)])


def _ink(img: np.ndarray) -> np.ndarray:
    """Pixels that are not the white background."""
    return (img < 250).any(axis=2)


def test_cloud_preview_draws_the_cloud_in_its_colours(tmp_path):
    """A cylinder seen side-on fills a box three times as tall as wide; the points whose value
    is at the top of the scale are drawn red, at the bottom blue (coolwarm)."""
    pts = _cylinder()
    values = np.where(pts[:, 0] > 0, 1.0, -1.0)  # +x half red, -x half blue
    path = cloud_preview(pts, values, tmp_path / "c.png", "cyl", "v", clim=(-1, 1),
                         cmap="coolwarm", camera=[(0, -100, 15), (0, 0, 15), (0, 0, 1)])
    img = cv2.imread(str(path))
    assert img.shape == (900, 900, 3)
    plot = _ink(img[50:840, 30:740])  # the plot area, without the title and colour bar
    ys, xs = np.nonzero(plot)
    height, width = np.ptp(ys) + 1, np.ptp(xs) + 1
    assert abs(height / width - 30 / 20) < 0.03
    assert plot.mean() > 0.5 * height * width / plot.size  # a filled silhouette, not a few dots
    # looking along +y with z up, +x is to the right: the right half red, the left half blue
    b, g, r = (img[50:840, 30:740][plot].astype(int)).T
    right = xs > xs.min() + 0.6 * width
    left = xs < xs.min() + 0.4 * width
    assert (r[right] > b[right] + 80).mean() > 0.95 and (b[left] > r[left] + 80).mean() > 0.95


def test_nearest_point_wins_each_pixel():
    """Two squares of points, the red one in front of the blue one (nearer the eye) whatever
    the order they are given in: where they overlap, every pixel is red."""
    g = np.stack(np.meshgrid(np.linspace(0, 10, 200), np.linspace(0, 10, 200)), -1).reshape(-1, 2)
    front = np.column_stack([g[:, 0], np.full(len(g), -5.0), g[:, 1]])
    back = np.column_stack([g[:, 0] + 5, np.full(len(g), 5.0), g[:, 1]])
    red, blue = np.tile([0, 0, 255], (len(g), 1)), np.tile([255, 0, 0], (len(g), 1))
    for order in ((front, back, red, blue), (back, front, blue, red)):
        canvas = raster.Canvas(camera=raster.Camera.looking((0, 1, 0), (0, 0, 1)))
        pts = np.concatenate(order[:2])
        canvas.fit(pts)
        raster.draw_points(canvas, pts, np.concatenate(order[2:]), size=4)  # no gaps
        (x0, y1), (x1, y0) = np.round(canvas.project(np.array([[5.5, 0, 0.5],
                                                                [9.5, 0, 9.5]]))[0]).astype(int)
        overlap = canvas.image[y0:y1, x0:x1].reshape(-1, 3)  # inside the overlap
        assert (overlap == (0, 0, 255)).all()


def _box_mesh(tmp_path: Path) -> Path:
    """A 20 × 10 × 30 mm box as a surface and as 6 tetrahedra per cube of a 2 × 1 × 3 grid."""
    from scipy.spatial import Delaunay

    g = np.stack(np.meshgrid(np.arange(3) * 10.0, np.arange(2) * 10.0, np.arange(4) * 10.0,
                             indexing="ij"), -1).reshape(-1, 3)
    tets = Delaunay(g + 1e-6 * np.random.default_rng(0).normal(size=g.shape)).simplices
    from dotshell.fem.meshes import boundary_faces_by_sorting, orient_positive

    tets = orient_positive(g, tets)
    surface = TriangleSurface(g, boundary_faces_by_sorting(tets))
    write_surface(tmp_path / "surface.ply", surface)
    write_volume(tmp_path / "volume.vtu", TetMesh(g, tets))
    return tmp_path


def test_mesh_previews_show_the_surface_and_the_cut_volume(tmp_path):
    """The surface and the half volume are drawn filled and shaded, with their edges; the half
    volume (y <= the centre) is about as tall and narrower in y than the whole."""
    d = _box_mesh(tmp_path)
    files = render_mesh_previews(d, tmp_path / "previews", "_1mm")
    assert set(files) == {"surface", "volume"}
    for name, path in files.items():
        img = cv2.imread(str(path))
        assert img.shape == (900, 900, 3) and path.name == f"{name}_1mm.png"
        plot = _ink(img[50:840, 30:870])
        assert plot.mean() > 0.15  # a filled picture
        dark = (img[50:840, 30:870] < 60).all(axis=2)
        assert 0.001 < dark.mean() < 0.1  # the edges: thin dark lines, not a black picture
        shades = np.unique(img[50:840, 30:870][plot & ~dark].sum(axis=1) // 30)
        assert len(shades) >= 3  # faces turned differently are shaded differently


def test_previews_load_no_opengl_renderer(tmp_path):
    """Drawing a cloud and a mesh preview imports neither pyvista nor VTK's rendering nor
    matplotlib (a fresh process: the test session may have imported them already)."""
    d = _box_mesh(tmp_path)
    code = (
        "import sys, json, numpy as np\n"
        "from pathlib import Path\n"
        "from dotshell.render.previews import cloud_preview\n"
        "from dotshell.render.mesh_previews import render_mesh_previews\n"
        "pts = np.random.default_rng(0).normal(size=(5000, 3))\n"
        f"cloud_preview(pts, None, Path({str(tmp_path / 'c.png')!r}))\n"
        f"render_mesh_previews(Path({str(d)!r}), Path({str(tmp_path / 'p')!r}))\n"
        "print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in "
        "('pyvista', 'vtkmodules', 'vtk', 'matplotlib'))))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout.splitlines()[-1]) == []
    assert (tmp_path / "c.png").stat().st_size > 1000


def test_colour_bar_middle_of_a_symmetric_range_reads_zero():
    """The colour bar's middle tick of a ±20 µm range is 0, not the sum's rounding noise."""
    lo, hi = -20.000000000000004, 20.0
    assert raster.tick_label((lo + hi) / 2, hi - lo) == "0"
    assert raster.tick_label(8.77e-3, 40.0) == "0.00877"
    assert raster.tick_label(-20.0, 40.0) == "-20"


def test_mesh_previews_of_the_meshes_in_hand_are_those_of_their_files(tmp_path):
    """The mesh step hands its surface and volume to the previews instead of reading the files
    it has just written: the same pictures, byte for byte, and no file is read (there is none)."""
    d = _box_mesh(tmp_path / "mesh")
    surface, volume = read_surface(d / "surface.ply"), read_volume(d / "volume.vtu")
    from_files = render_mesh_previews(d, tmp_path / "from_files")
    in_hand = render_mesh_previews(tmp_path / "no_such_dir", tmp_path / "in_hand",
                                   surface=surface, volume=volume)
    for name in ("surface", "volume"):
        assert from_files[name].read_bytes() == in_hand[name].read_bytes()
