"""The simulated world: BORG truth (placement, module offsets, partial deployment, displaced
tags), the true camera pose chain, seeding."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from lab.core.config import load_rig, parse_rig
from lab.core.errors import UserError
from lab.core.geometry import pose_error
from lab.core.rig_error import RigError
from lab.core.scenario import BorgFault, Scenario, load_scenario
from sim_devices.world import SimWorld

RIG = load_rig()
REPO = Path(__file__).resolve().parents[1]


def world(scenario: Scenario | None = None) -> SimWorld:
    return SimWorld(RIG, scenario, speedup=1000)


def test_only_placed_modules_have_tags():
    w = world()
    tt = set(w.borg.model.turntable.tag_ids)
    assert set(w.borg.visible_tag_ids()) == tt
    w.borg.place("1P")
    w.borg.place("2D")
    assert set(w.borg.visible_tag_ids()) == tt | {0, 1, 2}
    w.borg.remove("1P")
    assert 0 not in w.borg.visible_tag_ids()
    with pytest.raises(UserError, match="no BORG module named '99X'"):
        w.borg.place("99X")
    w.borg.place_all()
    assert len(w.borg.visible_tag_ids()) == 48


def test_module_offset_moves_all_its_tags_rigidly():
    w = world()
    design = {t: w.borg.model.tags[t].structure_T_tag for t in (1, 2)}
    w.borg.set_module_offset("2D", offset_m=[0.002, 0.0, -0.001])
    for t in (1, 2):
        assert w.borg.structure_T_tag(t).translation() - design[t].translation() == pytest.approx([0.002, 0, -0.001])
    anchor = w.borg.model.module_by_name["2D"].structure_T_module.translation()
    w.borg.set_module_offset("2D", rotation_rad=[0.0, 0.0, 0.01])
    assert w.borg.structure_T_module("2D").translation() == pytest.approx(anchor)   # turned about its anchor
    rel_design = design[1].between(design[2])
    rel_true = w.borg.structure_T_tag(1).between(w.borg.structure_T_tag(2))
    assert max(pose_error(rel_true, rel_design)) < 1e-12        # tags of one module keep their relation
    _, dr = pose_error(w.borg.structure_T_tag(1), design[1])
    assert dr == pytest.approx(0.01)


def test_partial_deployment_lowers_the_top_tag_only():
    w = world()
    b0, t0 = (w.borg.model.tags[t].structure_T_tag.translation() for t in (18, 19))   # 13D-B, 13D-T
    w.borg.set_deployed_height("13D", 0.35)
    assert w.borg.structure_T_tag(18).translation() == pytest.approx(b0)
    assert w.borg.structure_T_tag(19).translation() == pytest.approx(t0 - [0, 0, 0.15])
    assert w.borg.deployed_height_m("13D") == 0.35
    with pytest.raises(UserError, match="12S is a closeout_strut, not a deployable"):
        w.borg.set_deployed_height("12S", 0.3)
    with pytest.raises(UserError, match=r"must be in \(0, 0.5\] m, got 0.7 m"):
        w.borg.set_deployed_height("13D", 0.7)


def test_displaced_tag_moves_alone_in_structure_axes():
    w = world()
    before = {t: w.borg.structure_T_tag(t).translation() for t in (15, 16, 17)}
    w.borg.displace_tag(17, offset_m=[0.0, 0.3, 0.0])
    assert w.borg.structure_T_tag(17).translation() == pytest.approx(before[17] + [0, 0.3, 0])
    assert w.borg.structure_T_tag(15).translation() == pytest.approx(before[15])
    with pytest.raises(UserError, match="no tag 480"):
        w.borg.displace_tag(480, [0, 0, 0])


def test_the_issue_scenario_file_applies_its_structure_faults():
    scenario = load_scenario(REPO / "docs" / "scenarios" / "structure_faults.toml")
    w = world(scenario)
    model = w.borg.model
    assert w.seed == 7
    assert w.borg.deployed_height_m("13D") == pytest.approx(0.35)
    assert (w.borg.structure_T_tag(17).translation() - model.tags[17].structure_T_tag.translation()) == pytest.approx([0, 0.3, 0])
    tag_18s = model.module_by_name["18S"].tags[0]
    assert (w.borg.structure_T_tag(tag_18s).translation() - model.tags[tag_18s].structure_T_tag.translation()) == \
        pytest.approx([0.002, 0, 0])
    with pytest.raises(UserError, match="no BORG module named 'XD'"):
        world(Scenario(borg_faults=(BorgFault("partial_deploy", module="XD", height_m=0.3),)))


def test_true_camera_pose_follows_the_turntable_and_the_stewart():
    w = world(Scenario(rig_error=RigError()))      # an ideal rig: the true chain is the rig file's
    home_cam = w.world_T_camera()
    assert home_cam.translation() == pytest.approx([-2.95, 0.0, 0.75])
    tag = 1
    before = w.world_T_tag(tag)
    w.turntable.set_position(math.radians(90))
    after = w.world_T_tag(tag)
    Rz90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    assert after.translation() == pytest.approx(Rz90 @ before.translation())     # turned about the axis
    assert np.linalg.norm(after.translation() - before.translation()) > 0.1
    g = RIG.stewart.geometry
    raised = np.linalg.norm(g.home_m + [0, 0, 0.03] + g.platform_joints_m - g.base_joints_m, axis=1)
    w.stewart_legs.set_position(raised)
    assert w.world_T_camera().translation() == pytest.approx([-2.95, 0.0, 0.78], abs=1e-7)


def test_seeding_is_reproducible_and_streams_are_independent():
    a, b = world(Scenario(seed=4)), world(Scenario(seed=4))
    c = world(Scenario(seed=5))
    assert a.ipjrs["ipjr2"].step_scale == b.ipjrs["ipjr2"].step_scale != c.ipjrs["ipjr2"].step_scale
    assert a.ipjrs["ipjr1"].step_scale != a.ipjrs["ipjr2"].step_scale
    assert [a.ipjrs["ipjr1"].volts() for _ in range(5)] == [b.ipjrs["ipjr1"].volts() for _ in range(5)]


def test_a_hardware_rig_cannot_be_simulated():
    import tomllib

    from lab.core.config import default_rig_path

    data = tomllib.loads(default_rig_path().read_text())
    data.pop("sim")
    hw = parse_rig(data, "hw.toml", default_rig_path().parent)
    with pytest.raises(UserError, match="no \\[sim\\] table"):
        SimWorld(hw)
