"""Rig files: the packaged simulated rig loads; bad files get errors naming the key and problem."""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest

from lab.core.config import RigError, default_rig_path, load_rig, parse_rig
from lab.core.errors import UserError
from lab.core.geometry import Pose3, Rot3


def sim_data() -> dict:
    return tomllib.loads(default_rig_path().read_text())


def test_default_rig_is_the_simulated_bench():
    rig = load_rig()
    assert rig.simulated and rig.name == "sim"
    kinds = {name: kind for name, kind, _ in rig.devices()}
    assert kinds == {"turntable": "turntable", "stewart": "stewart", "lift": "lift", "camera": "camera",
                     "ipjr1": "ipjr", "ipjr2": "ipjr", "ipjr3": "ipjr"}
    assert (rig.lift.min_m, rig.lift.max_m) == (-0.5, 4.5)
    assert rig.turntable.min_rad == pytest.approx(math.radians(-90))
    assert rig.ipjrs["ipjr1"].step_m == pytest.approx(0.138e-3)        # the paper's d_step
    assert rig.ipjrs["ipjr1"].tolerance_m == pytest.approx(0.5e-3)     # the paper's 0.5 mm
    assert rig.ipjrs["ipjr3"].link.url.startswith("socket://")          # the Arduino transport
    assert rig.camera.calibration is not None and rig.camera.calibration.exists()
    g = rig.stewart.geometry
    legs = np.linalg.norm(g.home_m + g.platform_joints_m - g.base_joints_m, axis=1)
    assert np.allclose(legs, legs[0]) and g.leg_min_m < legs[0] < g.leg_max_m


def test_camera_sits_in_front_of_face_1_at_mid_height():
    rig = load_rig()
    base_T_platform_home = Pose3(Rot3(), rig.stewart.geometry.home_m)
    cam = rig.stewart.world_T_base.compose(base_T_platform_home).compose(rig.camera.platform_T_camera)
    assert cam.translation() == pytest.approx([-2.95, 0.0, 0.75])
    forward = cam.rotation().matrix()[:, 2]           # OpenCV z: the viewing direction
    assert forward == pytest.approx([1.0, 0.0, 0.0], abs=1e-9)   # towards face 1 (x = -0.75 m)
    down = cam.rotation().matrix()[:, 1]
    assert down == pytest.approx([0.0, 0.0, -1.0], abs=1e-9)


def test_calibration_file_matches_the_true_sim_camera():
    from drivers.camera import load_calibration

    rig = load_rig()
    cal = load_calibration(rig.camera.calibration)
    c = rig.sim.camera
    assert (cal.width_px, cal.height_px) == (c["width_px"], c["height_px"])
    assert cal.K[0, 0] == c["fx_px"] and cal.K[1, 2] == c["cy_px"]
    assert list(cal.dist) == c["dist"]
    assert 69 < cal.hfov_deg < 71


@pytest.mark.parametrize("mutate, key, problem", [
    (lambda d: d["turntable"].update(max_deg="lots"), "[turntable].max_deg", "expected a number in deg, got 'lots'"),
    (lambda d: d["turntable"].update(max_deg=-100.0), "[turntable].max_deg", "must be greater than min_deg"),
    (lambda d: d["turntable"].pop("url"), "[turntable].url", "missing (required)"),
    (lambda d: d["turntable"].update(spede=3), "[turntable].spede", "unknown key"),
    (lambda d: d["stewart"].update(leg_max_m=0.40), "[stewart].home_height_m", "outside [leg_min_m, leg_max_m]"),
    (lambda d: d["stewart"]["world_T_base"].update(xyz_m=[1, 2]), "[stewart.world_T_base].xyz_m", "a list of 3 numbers"),
    (lambda d: d["ipjr"]["ipjr1"].update(step_m=0.2), "[ipjr.ipjr1].step_m", "must be smaller than stroke_m"),
    (lambda d: d["ipjr"]["ipjr2"].update(tolerance_m=0.00001), "[ipjr.ipjr2].tolerance_m", "below half a step"),
    (lambda d: d["ipjr"]["ipjr1"].update(max_tries=0), "[ipjr.ipjr1].max_tries", "must be >= 1"),
    (lambda d: d["camera"].update(calibration="nowhere.json"), "[camera].calibration", "no such file"),
    (lambda d: d["sim"].update(speedup=0), "[sim].speedup", "must be > 0"),
    (lambda d: d["sim"]["camera"].update(dist="barrel"), "[sim.camera].dist", "a list of"),
    (lambda d: d["turntable"].update(retries=True), "[turntable].retries", "expected an integer"),
])
def test_bad_rig_names_the_key_and_the_problem(mutate, key, problem):
    data = sim_data()
    mutate(data)
    with pytest.raises(RigError) as err:
        parse_rig(data, source="bad.toml", base_dir=default_rig_path().parent)
    msg = str(err.value)
    assert msg.startswith("rig bad.toml: ") and key in msg and problem in msg, msg
    assert isinstance(err.value, UserError)  # the CLI prints it in one line, exit code 2


def test_duplicate_device_names_and_empty_rigs_are_refused():
    data = sim_data()
    data["ipjr"]["turntable"] = dict(data["ipjr"]["ipjr1"])
    with pytest.raises(RigError, match="device name 'turntable' already used"):
        parse_rig(data, "dup.toml", default_rig_path().parent)
    with pytest.raises(RigError, match="no devices"):
        parse_rig({"rig": {"name": "x"}}, "empty.toml")


def test_explicit_stewart_joints_are_accepted(tmp_path):
    rig = load_rig()
    g = rig.stewart.geometry
    data = sim_data()
    for k in ("base_radius_m", "base_half_angle_deg", "platform_radius_m", "platform_half_angle_deg"):
        data["stewart"].pop(k)
    data["stewart"]["base_joints_m"] = g.base_joints_m.tolist()
    data["stewart"]["platform_joints_m"] = g.platform_joints_m.tolist()
    rig2 = parse_rig(data, "explicit.toml", default_rig_path().parent)
    assert np.allclose(rig2.stewart.geometry.base_joints_m, g.base_joints_m)
    data["stewart"]["base_radius_m"] = 0.3  # mixing the two forms is a mistake
    with pytest.raises(RigError, match=r"\[stewart\].base_radius_m: unknown key"):
        parse_rig(data, "mixed.toml", default_rig_path().parent)


def test_missing_file_and_bad_toml(tmp_path):
    with pytest.raises(RigError, match="no such file"):
        load_rig(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[turntable\nurl = 1")
    with pytest.raises(RigError, match="not valid TOML"):
        load_rig(bad)


def test_with_urls_rewrites_only_the_named_devices():
    rig = load_rig()
    moved = rig.with_urls({"ipjr1": "http://127.0.0.1:1", "turntable": "socket://127.0.0.1:2"})
    assert moved.ipjrs["ipjr1"].link.url == "http://127.0.0.1:1"
    assert moved.turntable.link.url == "socket://127.0.0.1:2"
    assert moved.ipjrs["ipjr2"].link.url == rig.ipjrs["ipjr2"].link.url
    with pytest.raises(KeyError):
        rig.with_urls({"laser": "x"})


def test_the_hardware_template_is_a_valid_rig_before_any_calibration_exists():
    """First day on hardware (issue 12): the template loads as shipped; it names no calibration file
    that does not exist yet, and naming one that does not exist is still refused."""
    path = default_rig_path().parent / "hardware_example.toml"
    rig = load_rig(path)
    assert rig.camera.calibration is None and rig.calibration.file is None
    data = tomllib.loads(path.read_text())
    data["camera"]["calibration"] = "camera_calibration.json"
    with pytest.raises(RigError, match=r"\[camera\].calibration: no such file"):
        parse_rig(data, str(path), base_dir=path.parent)
    assert not rig.simulated and rig.ipjrs["ipjr3"].link.url == "/dev/ttyACM0"
    legs = np.linalg.norm(rig.stewart.geometry.home_m + rig.stewart.geometry.platform_joints_m
                          - rig.stewart.geometry.base_joints_m, axis=1)
    assert np.allclose(legs, 0.4243, atol=1e-4)
