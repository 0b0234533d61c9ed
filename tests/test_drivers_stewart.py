"""Stewart platform: IK (the issue's formula), workspace check reasons, FK (Newton) against the
simulator's independent FK, `lab stewart ik --json`, and moves against the simulator."""

from __future__ import annotations

import dataclasses
import json
import math
import re

import numpy as np
import pytest

from drivers.errors import RigMismatch, WorkspaceError
from drivers.stewart import Stewart
from drivers.stewart_kinematics import StewartKinematics
from lab.cli import main
from lab.core.comms import MemoryComms
from lab.core.config import load_rig
from lab.core.geometry import from_xyzrpy, pose_error, to_xyzrpy
from lab.core.rig_error import RigError
from lab.core.scenario import Scenario
from sim_devices.stewart import platform_pose

RIG = load_rig()
# the bench (tests/conftest.py) on an ideal rig: these tests compare the driver's kinematics with the
# simulator's, not the rig file with the truth (tests/test_rig_error.py does that)
pytestmark = pytest.mark.sim_bench(scenario=Scenario(rig_error=RigError()))
KIN = StewartKinematics(RIG.stewart.geometry)


def random_reachable_poses(n: int, seed: int = 1) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        p = np.concatenate([rng.uniform(-0.05, 0.05, 3), rng.uniform(-0.2, 0.2, 3)])
        if KIN.inverse(p).reachable:
            out.append(p)
    return out


def test_ik_is_the_distance_from_base_joint_to_moved_platform_joint():
    g = RIG.stewart.geometry
    for pose in random_reachable_poses(5):
        R = from_xyzrpy(pose).rotation().matrix()
        want = [np.linalg.norm(g.home_m + pose[:3] + R @ t - b) for t, b in zip(g.platform_joints_m, g.base_joints_m)]
        assert KIN.inverse(pose).legs_m == pytest.approx(want, abs=1e-12)


def test_fk_inverts_ik_and_agrees_with_the_simulators_own_fk():
    for pose in random_reachable_poses(8, seed=2):
        legs = KIN.inverse(pose).legs_m
        newton = KIN.forward(legs)
        assert to_xyzrpy(newton) == pytest.approx(pose, abs=1e-9)
        sim = platform_pose(RIG.stewart.geometry, legs)          # scipy least squares, written separately
        dt, dr = pose_error(newton, sim)
        assert dt < 1e-8 and dr < 1e-8


@pytest.mark.parametrize("pose, reason", [
    ([0, 0, 0.2, 0, 0, 0], r"leg \d length 0\.6165 m above leg_max_m 0\.5000 m"),
    ([0.05, -0.09, -0.18, -0.77, 0.5, 0.66], r"leg 1 length 0\.2269 m below leg_min_m 0\.3600 m"),
    ([-0.07, -0.05, 0.0, -0.04, 0.52, -0.52], r"base joint 6 angle 41\.31 deg above base_joint_max_deg 40\.00 deg"),
    ([0.04, -0.02, -0.02, -0.28, -0.35, -0.02], r"platform joint 2 angle 54\.82 deg above platform_joint_max_deg 45\.00 deg"),
    ([0, 0, 0, math.pi, 0, 0], r"platform inverted"),
    ([0, 0, -0.5, 0, 0, 0], r"platform joint \d at or below the base plane"),
])
def test_workspace_check_names_the_first_violated_limit(pose, reason):
    res = KIN.inverse(pose)
    assert not res.reachable
    assert re.search(reason, res.reason), res.reason


def test_lab_stewart_ik_json_shape(capsys):
    assert main(["stewart", "ik", "0.01", "-0.02", "0.015", "0.05", "-0.03", "0.1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) == {"pose", "legs_m", "reachable", "reason", "base_joints_m", "top_joints_m", "home_m"}
    assert out["pose"] == [0.01, -0.02, 0.015, 0.05, -0.03, 0.1]
    assert out["reachable"] is True and out["reason"] == ""
    assert len(out["legs_m"]) == 6 and len(out["base_joints_m"]) == 6 and len(out["top_joints_m"]) == 6
    home, base, top = np.array(out["home_m"]), np.array(out["base_joints_m"]), np.array(out["top_joints_m"])
    R = from_xyzrpy(out["pose"]).rotation().matrix()
    want = [np.linalg.norm(home + np.array(out["pose"][:3]) + R @ t - b) for t, b in zip(top, base)]
    assert out["legs_m"] == pytest.approx(want, abs=1e-12)

    assert main(["stewart", "ik", "0", "0", "0.2", "0", "0", "0", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["reachable"] is False and "above leg_max_m" in out["reason"]


def test_lab_stewart_ik_with_a_rig_file(tmp_path, capsys):
    from lab.core.config import default_rig_path

    text = default_rig_path().read_text().replace("home_height_m = 0.40", "home_height_m = 0.42")
    text = text.replace('calibration = "sim_camera.json"', f'calibration = "{default_rig_path().parent / "sim_camera.json"}"')
    rig = tmp_path / "r.toml"
    rig.write_text(text)
    assert main(["stewart", "ik", "0", "0", "0", "0", "0", "0", "--rig", str(rig), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["home_m"] == [0.0, 0.0, 0.42]


def test_moves_put_the_true_camera_where_the_driver_says(bench):
    st = Stewart.open(bench.rig.stewart, MemoryComms())
    assert st.identify().startswith("STEWART")
    for pose in random_reachable_poses(3, seed=5):
        reached = st.move_to(pose)
        dt, dr = pose_error(reached, from_xyzrpy(pose))
        assert dt < 2e-6 and dr < 2e-5                    # leg lengths travel with 1 um resolution
        true_cam = bench.world.world_T_camera()
        driver_cam = st.world_T_camera(reached, bench.rig.camera.platform_T_camera)
        dt, dr = pose_error(driver_cam, true_cam)
        assert dt < 1e-5 and dr < 1e-5
    assert to_xyzrpy(st.home()) == pytest.approx(np.zeros(6), abs=1e-5)
    st.close()


def test_unreachable_pose_is_refused_before_sending(bench):
    comms = MemoryComms()
    st = Stewart.open(bench.rig.stewart, comms)
    with pytest.raises(WorkspaceError, match=r"pose \(x 0\.0000, y 0\.0000, z 0\.2000 m.*unreachable: leg"):
        st.move_to([0, 0, 0.2, 0, 0, 0])
    assert not [r for r in comms.records if r.direction == "tx"]


def test_rig_leg_limits_beyond_the_hardware_stroke_are_a_mismatch(bench):
    g = dataclasses.replace(bench.rig.stewart.geometry, leg_max_m=0.6)
    st = Stewart.open(dataclasses.replace(bench.rig.stewart, geometry=g))
    with pytest.raises(RigMismatch, match=r"exceed the hardware stroke \[350, 510\] mm"):
        st.move_to([0, 0, 0.01, 0, 0, 0])
