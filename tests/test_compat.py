import numpy as np

from dotshell.runtime.compat import import_open3d


def test_open3d_imports_with_bundled_libusb_and_mesh_scene_raycasts():
    from dotshell_sim.scene import MeshShape

    o3d = import_open3d()
    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=5.0, resolution=64)
    shape = MeshShape(np.asarray(sphere.vertices), np.asarray(sphere.triangles))
    t, normal = shape.intersect(np.array([[0.0, 0.0, -50.0], [0.0, 20.0, -50.0]]),
                                np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]))[:2]
    assert abs(t[0] - 45.0) < 0.01 and normal[0, 2] < -0.99  # faceted sphere: ~µm off
    assert not np.isfinite(t[1]) or t[1] > 1e6  # the miss
