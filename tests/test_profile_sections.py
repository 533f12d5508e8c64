"""The profile's core sections as typed objects: one field per schema key, built once by
load_profile, read-only."""

import dataclasses

import pytest

from conftest import small_profile_dict
from dotshell.profile.loader import SCHEMA, validate_profile
from dotshell.profile.sections import SECTIONS, Section


def _schema_keys(schema):
    return {k: (_schema_keys(s.schema) if s.kind == "table" and s.schema else None)
            for k, s in schema.items()}


def _field_keys(section):
    return {f.name: (_field_keys(getattr(section, f.name))
                     if isinstance(getattr(section, f.name), Section) else None)
            for f in dataclasses.fields(section)}


@pytest.fixture
def profile(pm):
    raw = small_profile_dict(views=5)
    raw["processing"] = {"roi": {"radius_mm": 12.5}}
    raw["mesh"] = {"optics": {"musp_per_mm": 0.8}, "also_node_distances_mm": [2.0]}
    return validate_profile(raw, pm, "p.toml")


def test_every_section_has_exactly_the_schemas_keys(profile):
    """A key added to SCHEMA without its field (or the reverse) fails here, by name."""
    for name in SECTIONS:
        section = getattr(profile, "info" if name == "profile" else name)
        assert _field_keys(section) == _schema_keys(SCHEMA[name].schema), name


def test_sections_hold_the_validated_values_with_defaults(profile):
    assert profile.scan.views == 5 and profile.scan.exposure_ms == 20.0
    assert profile.angles_deg() == [0.0, 72.0, 144.0, 216.0, 288.0]
    assert profile.processing.roi.radius_mm == 12.5
    assert profile.processing.roi.z_max_mm == SCHEMA["processing"].schema["roi"].schema[
        "z_max_mm"].default
    assert profile.mesh.optics.musp_per_mm == 0.8 and profile.mesh.optics.mua_per_mm == 0.01
    assert profile.mesh.also_node_distances_mm == (2.0,)
    assert profile.name == profile.info.name == profile.data["profile"]["name"]
    # the sections read as the raw tables do, for code written against them
    assert dict(profile.processing.roi) == profile.data["processing"]["roi"]
    assert profile.mesh.as_table() == profile.data["mesh"]
    assert profile.scan["retries"] == profile.scan.retries == 2


def test_profile_cannot_be_changed_through_its_sections_or_data(profile):
    with pytest.raises(dataclasses.FrozenInstanceError):
        profile.scan.views = 7  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        profile.scan = profile.scan  # type: ignore[misc]
    raw = profile.data
    raw["scan"]["views"] = 99
    raw["camera"]["settings"]["width"] = 1
    assert profile.data["scan"]["views"] == 5 and profile.scan.views == 5
    assert profile.data["camera"]["settings"]["width"] != 1
    with pytest.raises(KeyError):
        profile.scan["no_such_key"]


def test_run_layout_names_match_the_documented_run_directory():
    """The names RunLayout gives are those of docs/run-directory.md (the on-disk contract)."""
    from dotshell.run.layout import RunLayout as L

    assert (L.CALIBRATION, L.PROFILE, L.MANIFEST, L.EVENTS, L.REPORT, L.CLOUD) == (
        "calibration.json", "profile.toml", "manifest.json", "events.jsonl", "report.json",
        "cloud.ply")
    assert L.frame_stack(7) == "frames/view_007.tif"
    assert L.frame_info(7) == "frames/view_007/frame_info.json"
    assert L.view_cloud(12) == "views/view_012.ply" and L.view_record(12) == "views/view_012.json"
    assert L.view_preview("columns", 0) == "previews/columns_view_000.png"
    assert L.trans_frame("src_01", 2) == "transillumination/view_002/src_01.png"
    assert L.trans_frame("flat") == "transillumination/flat.png"
    assert L.mesh_dir(0.5) == "meshes/0.5mm" and L.generation_dir(3) == "gen/003"
    assert L.set_aside(1, 2) == "frames/view_001.partial-2"
    assert L.view_index(L.view_stem(42)) == 42
    assert L.png_frame(3, "col_02") == "003_col_02.png"
