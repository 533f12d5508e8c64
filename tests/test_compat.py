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


def test_open3d_imports_without_its_plotly_drawing_until_it_is_used():
    """import_open3d defers open3d.visualization.draw_plotly (dash and plotly: ~0.35 s of
    CPU in every process importing open3d, unused by dotshell); a call of one of its functions
    imports it and answers as open3d would. A fresh process: the test session may hold dash."""
    import json
    import subprocess
    import sys

    code = """
import json, sys
import numpy as np
from dotshell.runtime.compat import import_open3d
o3d = import_open3d()
web = lambda: sorted({m.split('.')[0] for m in sys.modules} & {'dash', 'plotly'})
pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.eye(3)))
pcd = pcd.voxel_down_sample(0.1)
before = web()
fig = o3d.visualization.get_plotly_fig([pcd])
print(json.dumps({"before": before, "after": web(), "figure": type(fig).__name__,
                  "points": len(fig.data[0].x)}))
"""
    r = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout.splitlines()[-1])
    assert out["before"] == []
    assert out["after"] == ["dash", "plotly"]
    assert out["figure"] == "Figure" and out["points"] == 3
