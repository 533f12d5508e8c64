"""Property tests of the file readers: random input and valid files with random damage (bytes
flipped, inserted, cut; JSON or TOML values replaced or deleted) are read or refused with a named
:class:`~dotshell.errors.DotshellError` — never another exception. What is read is usable: the
checks the commands rely on hold for it.

Readers: point clouds (PLY), calibrations (dotshell JSON, OpenCV YAML/XML), run manifests,
profiles (TOML and ``--set``), layouts, the event log, surface/volume meshes and optodes, frames.
Example counts are modest (the suite stays fast); ``--hypothesis-seed`` reproduces a failure.
"""

from __future__ import annotations

import copy
import functools
import json
import math
import tempfile
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest
import tomli_w
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from conftest import ROOT
from dotshell.errors import DotshellError

FAST = settings(max_examples=120, deadline=None, suppress_health_check=list(HealthCheck))
SLOW = settings(max_examples=30, deadline=None, suppress_health_check=list(HealthCheck))

# ---- strategies ---------------------------------------------------------------------------------

numbers = (st.integers(-2**40, 2**40) | st.floats(allow_nan=True, allow_infinity=True)
           | st.sampled_from([0, -1, 1, 1e300, -0.0]))
json_scalars = st.none() | st.booleans() | numbers | st.text(max_size=8)
json_values = st.recursive(json_scalars, lambda inner: st.lists(inner, max_size=4)
                           | st.dictionaries(st.text(max_size=8), inner, max_size=4),
                           max_leaves=10)
toml_values = st.recursive(
    st.booleans() | st.integers(-2**40, 2**40) | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(
        st.text(min_size=1, max_size=8), inner, max_size=4), max_leaves=10)


def mutate_tree(data: st.DataObject, doc: Any, values: st.SearchStrategy = json_values,
                max_changes: int = 3) -> Any:
    """``doc`` with 1..max_changes random nodes replaced by ``values`` or deleted."""
    doc = copy.deepcopy(doc)
    for _ in range(data.draw(st.integers(1, max_changes))):
        doc = _mutate_node(data, doc, values)
    return doc


def _mutate_node(data: st.DataObject, node: Any, values: st.SearchStrategy) -> Any:
    if isinstance(node, (dict, list)) and node and data.draw(st.integers(0, 3)) > 0:
        keys = list(node) if isinstance(node, dict) else list(range(len(node)))
        key = data.draw(st.sampled_from(keys))
        action = data.draw(st.sampled_from(["descend", "descend", "delete", "replace"]))
        if action == "descend":
            node[key] = _mutate_node(data, node[key], values)
        elif action == "delete":
            del node[key]
        else:
            node[key] = data.draw(values)
        return node
    return data.draw(values)


def mutate_bytes(data: st.DataObject, blob: bytes, max_changes: int = 4) -> bytes:
    """``blob`` with random bytes flipped, inserted or removed, or cut short."""
    b = bytearray(blob)
    for _ in range(data.draw(st.integers(1, max_changes))):
        if not b:
            break
        i = data.draw(st.integers(0, len(b) - 1))
        op = data.draw(st.sampled_from(["flip", "insert", "delete", "cut", "digit"]))
        if op == "flip":
            b[i] = data.draw(st.integers(0, 255))
        elif op == "insert":
            b[i:i] = data.draw(st.binary(min_size=1, max_size=8))
        elif op == "delete":
            del b[i:i + data.draw(st.integers(1, 16))]
        elif op == "digit":  # numbers in text formats: the interesting damage
            b[i] = data.draw(st.sampled_from(b"0123456789-.eE"))
        else:
            del b[i:]
    return bytes(b)


#: every file these tests write lives under one folder, removed when the test process exits
#: (weakref.finalize of TemporaryDirectory), so hypothesis' many examples leave nothing in /tmp
_SCRATCH = tempfile.TemporaryDirectory(prefix="dotshell-readers-")


def scratch_dir() -> Path:
    """A fresh empty folder under this module's scratch folder."""
    return Path(tempfile.mkdtemp(dir=_SCRATCH.name))


def in_file(content: bytes | str, name: str) -> Path:
    d = scratch_dir()
    p = d / name
    p.write_bytes(content.encode() if isinstance(content, str) else content)
    return p


def refused_or(read: Callable[[], Any], check: Callable[[Any], None] | None = None) -> None:
    """``read()`` either raises a DotshellError or returns something ``check`` accepts."""
    try:
        value = read()
    except DotshellError as exc:
        assert str(exc), "an error without a message"
        return
    if check is not None:
        check(value)


# ---- point clouds -------------------------------------------------------------------------------

def _valid_ply() -> bytes:
    from dotshell.run.ply import write_ply

    p = in_file(b"", "seed.ply")
    write_ply(p, np.arange(30, dtype=float).reshape(10, 3), view=np.arange(10))
    return p.read_bytes()


PLY = _valid_ply()


def _cloud_ok(value) -> None:
    pts, scalars = value
    assert pts.ndim == 2 and pts.shape[1] == 3 and np.isfinite(pts).all()
    assert all(len(v) == len(pts) for v in scalars.values())


@FAST
@given(st.data())
def test_ply_reader_on_damaged_clouds(data):
    from dotshell.run.ply import read_ply

    head_end = PLY.index(b"end_header\n") + 11
    blob = data.draw(st.sampled_from(["header", "anywhere"]))
    damaged = (mutate_bytes(data, PLY[:head_end]) + PLY[head_end:] if blob == "header"
               else mutate_bytes(data, PLY))
    refused_or(lambda: read_ply(in_file(damaged, "c.ply")), _cloud_ok)


@FAST
@given(st.binary(max_size=300) | st.text(max_size=200).map(lambda t: ("ply\n" + t).encode()))
def test_ply_reader_on_random_bytes(blob):
    from dotshell.run.ply import read_ply

    refused_or(lambda: read_ply(in_file(blob, "c.ply")), _cloud_ok)


# ---- calibrations -------------------------------------------------------------------------------

def _valid_calibration() -> dict:
    from dotshell.geometry.calibration import RigCalibration
    from dotshell.geometry.lens import lens_from_fov

    c = RigCalibration(lens_from_fov(128, 102, 640.0, (-0.08, 0.1, 0, 0, 0)),
                       lens_from_fov(102, 77, 448.0), np.eye(3), [-80.0, 4.0, 6.0],
                       [0.0, 15.0, 204.0], [0.0, -0.96, -0.26], "seed")
    return c.to_dict()


CALIBRATION = _valid_calibration()


def _calibration_ok(calib) -> None:
    assert calib.problem() == ""
    assert calib.camera.width >= 1 and calib.camera.height >= 1
    pts = calib.sample_to_camera(np.array([[0.0, 0.0, 10.0]]), 30.0)
    assert np.isfinite(pts).all() and np.isfinite(calib.stage_basis()).all()


@FAST
@given(st.data())
def test_calibration_json_reader(data):
    from dotshell.geometry.calibration import RigCalibration

    doc = data.draw(st.sampled_from(["mutated", "random"]))
    value = mutate_tree(data, CALIBRATION) if doc == "mutated" else data.draw(json_values)
    text = json.dumps(value)
    refused_or(lambda: RigCalibration.load(in_file(text, "cal.json")), _calibration_ok)


@FAST
@given(st.data())
def test_calibration_json_text_damage(data):
    from dotshell.geometry.calibration import RigCalibration

    text = mutate_bytes(data, json.dumps(CALIBRATION, indent=1).encode())
    refused_or(lambda: RigCalibration.load(in_file(text, "cal.json")), _calibration_ok)


@SLOW
@given(st.data(), st.sampled_from(["yml", "xml"]))
def test_opencv_calibration_reader(data, suffix):
    from dotshell.geometry.calibration import RigCalibration
    from dotshell.geometry.opencv_io import read_opencv_calibration, write_opencv_calibration

    seed = write_opencv_calibration(RigCalibration.from_dict(CALIBRATION),
                                    in_file(b"", f"seed.{suffix}")).read_bytes()
    damaged = mutate_bytes(data, seed)
    refused_or(lambda: read_opencv_calibration(in_file(damaged, f"cal.{suffix}")),
               _calibration_ok)


# ---- run manifests ------------------------------------------------------------------------------

def _valid_manifest() -> dict:
    from dotshell.run.store import RunStore

    store = RunStore(scratch_dir())
    store.init_manifest("seed", [0.0, 180.0], ["white", "black", "col_00", "col_00_inv"])
    m = store.manifest
    m["views"][0].update(frames=4, complete=True, angle_read_deg=0.01)
    m["views"][1].update(frames=2)
    m["shots"] = [{"name": n, "pattern": i, "analyzer_deg": None}
                  for i, n in enumerate(m["frame_names"])]
    m["camera"] = {"width": 128, "height": 102, "bit_depth": 12}
    m["transillumination"] = {"exposure_ms": 50.0, "camera_bit_depth": 12,
                              "targets_mm": [[0.0, 10.0]], "frame_names": ["src_00"],
                              "flat_field": None, "views": {"0": ["src_00"]}}
    return m


MANIFEST = _valid_manifest()


def _manifest_ok(m) -> None:
    """What the commands do with a manifest that passed the check, they can do."""
    from dotshell.run.framecheck import FrameSpec
    from dotshell.pipeline.pdi import shots_from_manifest
    from dotshell.pipeline.steps import view_angle

    names = m["frame_names"]
    for v in m["views"]:
        assert 0 <= v["frames"] <= len(names) and math.isfinite(view_angle(v))
    shots = shots_from_manifest(m)
    assert [s.name for s in shots] == names
    if m.get("camera") is not None:  # null: a run made before it was recorded
        FrameSpec.from_dict(m["camera"])
    t = m.get("transillumination")
    if t is not None:
        assert t["exposure_ms"] > 0 and all(isinstance(v, list) for v in t["views"].values())
        [int(k) for k in t["views"]]


@FAST
@given(st.data())
def test_manifest_check(data):
    from dotshell.run.store import check_manifest

    doc = data.draw(st.sampled_from(["mutated", "mutated", "random"]))
    m = mutate_tree(data, MANIFEST) if doc == "mutated" else data.draw(json_values)
    m = json.loads(json.dumps(m))  # as read from the file
    refused_or(lambda: check_manifest(m, Path("manifest.json")), _manifest_ok)


@FAST
@given(st.data())
def test_manifest_file_damage(tmp_path_factory, data):
    from dotshell.run.store import RunStore

    run = tmp_path_factory.mktemp("run")
    (run / "manifest.json").write_bytes(mutate_bytes(data, json.dumps(MANIFEST).encode()))
    store = RunStore.open(run)
    refused_or(lambda: store.manifest, _manifest_ok)
    refused_or(store.status)


# ---- profiles and --set ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def pm():
    from dotshell.plugins import PluginManager

    m = PluginManager()
    m.load_entry_points()
    return m


def _profile_raw() -> dict:
    from fault_harness import tiny_profile_dict

    return tiny_profile_dict()


PROFILE = _profile_raw()


def _profile_ok(profile) -> None:
    """A profile that validates can be written to a run (TOML) and gives usable angles."""
    text = tomli_w.dumps(profile.raw())
    assert text
    angles = profile.angles_deg()
    assert angles and all(math.isfinite(a) for a in angles)


@FAST
@given(st.data())
def test_profile_validation_of_damaged_values(pm, data):
    from dotshell.profile.loader import validate_profile

    raw = mutate_tree(data, PROFILE, toml_values)
    assume(isinstance(raw, dict))
    refused_or(lambda: validate_profile(raw, pm, "p.toml"), _profile_ok)


@FAST
@given(st.data())
def test_profile_file_damage(pm, data):
    from dotshell.profile.loader import load_profile

    text = mutate_bytes(data, tomli_w.dumps(PROFILE).encode(), max_changes=3)
    refused_or(lambda: load_profile(in_file(text, "p.toml"), pm), _profile_ok)


@FAST
@given(st.lists(st.text(max_size=24) | st.sampled_from(
    ["scan.views=3", "scan.views.x=1", "=1", "scan=[1", "camera=3", "scan.angles_deg=[nan]",
     "scan.exposure_ms=inf", "a.b.c.d=1", "scan.views=1e999", "profile.name={x=1}"]),
    max_size=3))
def test_set_overrides(pm, overrides):
    from dotshell.profile.loader import apply_overrides, validate_profile

    refused_or(lambda: validate_profile(apply_overrides(PROFILE, overrides, "p.toml"), pm,
                                        "p.toml"), _profile_ok)


# ---- layouts -------------------------------------------------------------------------------------

LAYOUT = (ROOT / "layouts" / "opencv-graycode.toml").read_bytes()


def _layout_ok(layout) -> None:
    names = [layout.file_name(i) for i in range(3)]
    assert all(isinstance(n, str) and n for n in names)


@FAST
@given(st.data())
def test_layout_reader(data):
    import tomllib

    from dotshell.run.capture_layouts import load_layout

    kind = data.draw(st.sampled_from(["bytes", "values"]))
    if kind == "bytes":
        text = mutate_bytes(data, LAYOUT)
    else:
        raw = mutate_tree(data, tomllib.loads(LAYOUT.decode()), toml_values)
        assume(isinstance(raw, dict))
        text = tomli_w.dumps(raw).encode()
    refused_or(lambda: load_layout(in_file(text, "layout.toml")), _layout_ok)


# ---- the event log ------------------------------------------------------------------------------

@FAST
@given(st.data())
def test_event_log_reader_never_fails(tmp_path_factory, data):
    from dotshell.run.store import RunStore

    run = tmp_path_factory.mktemp("run")
    good = b"".join(json.dumps({"event": "FrameCaptured", "view": i}).encode() + b"\n"
                    for i in range(5))
    (run / "events.jsonl").write_bytes(mutate_bytes(data, good))
    events = RunStore(run).events()
    assert all(isinstance(e, dict) for e in events)
    store = RunStore(run)  # and the next job appends whole lines after whatever is there
    store.append_event({"event": "Next"})
    store.close()
    assert RunStore(run).events()[-1] == {"event": "Next"}


# ---- meshes and optodes -------------------------------------------------------------------------

@functools.cache
def mesh_files() -> tuple[bytes, bytes]:
    """A valid surface (PLY) and volume (VTU) file's bytes, made at first use, not at
    collection: writing the volume computes its boundary (a numba kernel, in the workers of
    ``make test`` compiled only once the controller has compiled it, tests/conftest.py)."""
    from dotshell.fem.meshes import TetMesh, TriangleSurface
    from dotshell.fem.meshfiles import write_surface, write_volume

    nodes = 10.0 * np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    d = scratch_dir()
    write_surface(d / "s.ply", TriangleSurface(nodes, [[0, 2, 1], [0, 1, 3], [0, 3, 2],
                                                       [1, 2, 3]]))
    write_volume(d / "v.vtu", TetMesh(nodes, [[0, 1, 2, 3]], {"mua_per_mm": np.full(4, 0.01)}))
    return (d / "s.ply").read_bytes(), (d / "v.vtu").read_bytes()


def _surface_ok(s) -> None:
    assert np.isfinite(s.vertices).all() and len(s.triangles)
    assert s.triangles.min() >= 0 and s.triangles.max() < len(s.vertices)


def _volume_ok(m) -> None:
    assert np.isfinite(m.nodes).all() and len(m.tets)
    assert m.tets.min() >= 0 and m.tets.max() < len(m.nodes)
    m.boundary_nodes  # what exporters and the forward solver compute first


@SLOW
@given(st.data())
def test_surface_reader(data):
    from dotshell.fem.meshfiles import read_surface

    refused_or(lambda: read_surface(in_file(mutate_bytes(data, mesh_files()[0]), "surface.ply")),
               _surface_ok)


@SLOW
@given(st.data())
def test_volume_reader(data):
    from dotshell.fem.meshfiles import read_volume

    refused_or(lambda: read_volume(in_file(mutate_bytes(data, mesh_files()[1]), "volume.vtu")),
               _volume_ok)


OPTODES = {"units": "mm", "sources_mm": [[0.0, 0.0, 5.0]], "detectors_mm": [[5.0, 0.0, 5.0],
                                                                            [0.0, 5.0, 5.0]],
           "links": [[0, 0], [0, 1]]}


@FAST
@given(st.data())
def test_optodes_reader(data):
    from dotshell.fem.meshfiles import read_optodes

    doc = data.draw(st.sampled_from(["mutated", "random", "text"]))
    if doc == "text":
        text = mutate_bytes(data, json.dumps(OPTODES).encode())
    else:
        value = mutate_tree(data, OPTODES) if doc == "mutated" else data.draw(json_values)
        text = json.dumps(value).encode()

    def ok(o):
        assert np.isfinite(o.sources_mm).all() and np.isfinite(o.detectors_mm).all()
        if len(o.links):
            assert o.links[:, 0].max() < len(o.sources_mm)
            assert o.links[:, 1].max() < len(o.detectors_mm)

    refused_or(lambda: read_optodes(in_file(text, "optodes.json")), ok)


# ---- frames --------------------------------------------------------------------------------------

arrays = st.one_of(
    st.builds(lambda shape, dtype: np.zeros(shape, dtype),
              st.tuples(st.integers(0, 4), st.integers(0, 5)) | st.tuples(
                  st.integers(0, 4), st.integers(0, 5), st.integers(0, 4)) | st.just(()),
              st.sampled_from([np.uint8, np.uint16, np.int32, np.float32, np.bool_, np.float64])),
    st.builds(lambda v: np.full((4, 5), v, np.uint16), st.integers(0, 65535)),
    json_values)


@FAST
@given(arrays, st.sampled_from([8, 10, 12, 16]))
def test_frame_check(frame, bits):
    from dotshell.run.framecheck import FrameSpec, dtype_for

    spec = FrameSpec(5, 4, bits)

    def ok(f):
        assert f.shape == (4, 5) and f.dtype == dtype_for(bits)
        assert int(f.max()) < 1 << bits

    refused_or(lambda: spec.check(frame, "frame", "fix it"), ok)


def test_optodes_with_a_link_past_any_integer_are_refused(tmp_path):
    """Found by test_optodes_reader: a link of 9.2e18 overflowed the int64 conversion."""
    from dotshell.fem.meshfiles import read_optodes

    path = tmp_path / "optodes.json"
    path.write_text(json.dumps({**OPTODES, "links": 9.223372036854776e18}))
    with pytest.raises(DotshellError, match="not a valid optodes file"):
        read_optodes(path)
