import pytest

from dotshell.errors import ProfileError
from dotshell.settings import Setting, validate_settings

SCHEMA = {
    "width": Setting("int", min=16, max=8192, help="pixels", unit="px"),
    "gain": Setting("float", default=1.0, min=0.0),
    "mode": Setting("str", default="fast", choices=("fast", "slow")),
    "dist": Setting("list[float]", default=[0.0] * 5, length=5),
    "K": Setting("matrix", default=[[1, 0, 0], [0, 1, 0], [0, 0, 1]], length=(3, 3)),
    "sub": Setting("table", default={}, schema={"on": Setting("bool", default=False)}),
}


def test_defaults_filled_and_types_normalised():
    out = validate_settings(SCHEMA, {"width": 640, "gain": 2}, "p.toml", "camera.settings")
    assert out["width"] == 640 and out["gain"] == 2.0 and isinstance(out["gain"], float)
    assert out["mode"] == "fast" and out["dist"] == [0.0] * 5 and out["sub"] == {"on": False}


@pytest.mark.parametrize("data, fragment", [
    ({}, "missing required key [camera.settings.width]"),
    ({"width": "640"}, "[camera.settings.width] = '640' is invalid: expected an integer"),
    ({"width": 8}, "expected a value in [16, 8192] px"),
    ({"width": 64, "mode": "turbo"}, "Valid choices: 'fast', 'slow'"),
    ({"width": 64, "colour": 1}, "unknown key [camera.settings.colour]. Valid keys here: K, dist"),
    ({"width": 64, "dist": [0, 0]}, "a list of exactly 5 items"),
    ({"width": 64, "K": [[1, 0], [0, 1]]}, "a 3x3 matrix"),
    ({"width": 64, "sub": {"on": 1}}, "[camera.settings.sub.on] = 1 is invalid: expected true or false"),
    ({"width": True}, "expected an integer"),
])
def test_errors_name_file_key_value_and_fix(data, fragment):
    with pytest.raises(ProfileError) as e:
        validate_settings(SCHEMA, data, "p.toml", "camera.settings")
    assert str(e.value).startswith("p.toml: ")
    assert fragment in str(e.value)


def test_a_role_the_caller_needs_is_named_when_the_profile_lacks_it():
    from dotshell.plugins import get_plugin_manager
    from dotshell.profile.loader import load_profile

    p = load_profile("sim-metal-cylinder", get_plugin_manager())  # no light source
    assert p.required_role("camera")["backend"] == "sim-camera"
    assert p.role("light_source") is None
    with pytest.raises(ProfileError, match=r"sim-metal-cylinder.toml: no \[light_source\] "
                                           r"table; add one"):
        p.required_role("light_source")
