"""Robot profile TOML loading: shipped profiles load, units convert, bad input names the bad key."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from labcal.drivers.ur import load_ur_profile, parse_ur_profile

REPO = Path(__file__).resolve().parents[2]
SHIPPED = sorted((REPO / "drivers").glob("ur*.toml"))


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_shipped_profiles_load(path):
    profile = load_ur_profile(path)
    assert profile.limits.joint_limits.shape == (6, 2)
    assert profile.limits.max_speed <= 3.14 and profile.limits.max_acceleration <= 40


def test_shipped_profiles_exist():
    assert any(p.name == "ur10-lab.toml" for p in SHIPPED)


def base() -> dict:
    return tomllib.loads((REPO / "drivers" / "ur10-lab.toml").read_text())


def test_degrees_and_caps_convert_to_si():
    data = base()
    data["joint_limits_deg"]["lower"] = [-90.0, -180.0, -45.0, -360.0, -10.0, -1.0]
    data["motion"]["max_speed_rad_s"] = 0.25
    profile = parse_ur_profile(data)
    np.testing.assert_allclose(profile.limits.joint_limits[:, 0], np.radians([-90, -180, -45, -360, -10, -1]))
    assert profile.limits.max_speed == 0.25
    assert profile.with_host("127.0.0.9").host == "127.0.0.9"


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d["motion"].update(max_speed_rad_s=4.0), "max_speed_rad_s"),
        (lambda d: d["motion"].update(max_acceleration_rad_s2=-1), "max_acceleration_rad_s2"),
        (lambda d: d["motion"].update(max_sped_rad_s=0.1), r"max_sped_rad_s' \(did you mean 'max_speed_rad_s'\?\)"),
        (lambda d: d["ports"].update(rtde=30005), "always connects to port 30004"),
        (lambda d: d["joint_limits_deg"].update(lower=[0.0] * 5), r"lower must be a list of 6 numbers \(degrees\)"),
        (lambda d: d["joint_limits_deg"].update(upper=[720.0] * 6), "360"),
        (lambda d: d["joint_limits_deg"].update(lower=[0.0, 400.0, 0, 0, 0, 0]), "joint 2"),
        (lambda d: d.update(host=""), "host must not be empty"),
        (lambda d: d["timing"].update(frequency_hz=1000), "frequency_hz"),
        (lambda d: d.update(driver="sim"), "driver"),
    ],
)
def test_bad_profiles_name_the_bad_key(edit, message):
    data = base()
    edit(data)
    with pytest.raises(ValueError, match=message):
        parse_ur_profile(data)


def test_invalid_toml_names_the_file(tmp_path):
    path = tmp_path / "broken.toml"
    path.write_text("name = \n")
    with pytest.raises(ValueError, match=r"broken\.toml"):
        load_ur_profile(path)


def test_default_values_are_finite():
    profile = parse_ur_profile(
        {"name": "x", "host": "h", "joint_limits_deg": {"lower": [-1.0] * 6, "upper": [1.0] * 6}}
    )
    assert math.isfinite(profile.settle_time) and profile.frequency == -1.0


def write_model(tmp_path, limits_rad):
    joints = "".join(
        f"[[joints]]\ntype = 'revolute'\na = 0.1\nalpha = 0.0\nd = 0.1\ntheta = 0.0\nlimits = [{lo}, {hi}]\n"
        for lo, hi in limits_rad
    )
    path = tmp_path / "arm.toml"
    path.write_text(f"name = 'arm'\nkinematics = 'dh'\n{joints}")
    return str(path)


def test_model_limits_bound_the_profile(tmp_path):
    model = write_model(tmp_path, [(-1.0, 1.0)] * 6)
    # without [joint_limits_deg] the model's limits apply as they are
    profile = parse_ur_profile({"name": "x", "host": "h", "model": model})
    np.testing.assert_allclose(profile.limits.joint_limits, [[-1.0, 1.0]] * 6)
    # a profile may narrow them ...
    narrow = {"lower": [-10.0] * 6, "upper": [10.0] * 6}
    profile = parse_ur_profile({"name": "x", "host": "h", "model": model, "joint_limits_deg": narrow})
    np.testing.assert_allclose(profile.limits.joint_limits, np.radians([[-10.0, 10.0]] * 6))
    # ... but not widen them
    wide = {"lower": [-10.0, -90.0, -10.0, -10.0, -10.0, -10.0], "upper": [10.0] * 6}
    with pytest.raises(ValueError, match=r"joint 2.*beyond model"):
        parse_ur_profile({"name": "x", "host": "h", "model": model, "joint_limits_deg": wide})


def test_unknown_or_wrong_sized_model_is_rejected(tmp_path):
    with pytest.raises(ValueError, match="'model' = 'no-such-robot'"):
        parse_ur_profile({"name": "x", "host": "h", "model": "no-such-robot"})
    with pytest.raises(ValueError, match="has 5 joints"):
        parse_ur_profile({"name": "x", "host": "h", "model": write_model(tmp_path, [(-1.0, 1.0)] * 5)})
