"""The rig-error model of the simulated world: the true bench is the rig file plus errors the
software is not told (camera mount, Stewart base, turntable axis, turntable tags, lens, per-move
repeatability), from the rig's [sim.rig_error] or a scenario's [rig_error]."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lab.core.config import load_rig
from lab.core.errors import UserError
from lab.core.geometry import Pose3, Rot3
from lab.core.rig_error import RigError
from lab.core.scenario import Scenario, parse_scenario
from sim_devices.world import SimWorld

RIG = load_rig()


def world(error: RigError | None, seed: int = 0) -> SimWorld:
    return SimWorld(RIG, Scenario(seed=seed, rig_error=error), speedup=1000)


def test_the_default_sim_rig_has_errors_of_its_own_and_a_scenario_replaces_them():
    assert not RIG.sim.rig_error.ideal
    assert SimWorld(RIG, Scenario()).rig_error == RIG.sim.rig_error          # no [rig_error]: the rig's
    s = parse_scenario({"rig_error": {"focal_scale": 1.004}}, "s.toml")
    assert s.rig_error == RigError(focal_scale=1.004)                          # omitted keys are zero
    assert parse_scenario({"rig_error": {"ideal": True}}, "s.toml").rig_error.ideal


@pytest.mark.parametrize("table, message", [
    ({"mount_offset": [0, 0, 0]}, r"rig_error.mount_offset: unknown key"),
    ({"camera_mount_offset_m": [0.001, 0.0]}, r"rig_error.camera_mount_offset_m: expected a list of 3 finite numbers"),
    ({"camera_mount_offset_m": [5.0, 0.0, 0.0]}, r"camera_mount_offset_m: .* beyond 0.1 .*check the unit"),
    ({"focal_scale": float("nan")}, r"rig_error.focal_scale: expected a finite number"),
    ({"focal_scale": 1.5}, r"focal_scale: must be in \[0.9, 1.1\]"),
    ({"turntable_tag_sigma_m": -0.001}, r"turntable_tag_sigma_m: must be in \[0, 0.02\]"),
    ({"ideal": True, "focal_scale": 1.001}, r"rig_error.focal_scale: ideal = true means no rig error"),
])
def test_bad_rig_error_tables_are_named(table, message):
    with pytest.raises(UserError, match=message):
        parse_scenario({"rig_error": table}, "s.toml")


def test_an_ideal_rig_is_the_rig_file():
    w = world(RigError())
    assert w.world_T_camera().equals(RIG.stewart.world_T_base.compose(
        Pose3(Rot3(), RIG.stewart.geometry.home_m)).compose(RIG.camera.platform_T_camera), 1e-9)
    assert w.camera.K[0, 0] == RIG.sim.camera["fx_px"]


def test_mount_and_base_errors_move_the_true_camera_in_their_frames():
    nominal = world(RigError()).world_T_camera()
    mount = world(RigError(camera_mount_offset_m=(0.004, -0.003, 0.002))).world_T_camera()
    # at home the platform's axes are the world's: the mount offset shows up as is
    assert mount.translation() - nominal.translation() == pytest.approx([0.004, -0.003, 0.002], abs=1e-9)
    turned = world(RigError(camera_mount_rotation_rad=(0.0, 0.0, 0.01))).world_T_camera()
    assert turned.translation() == pytest.approx(nominal.translation(), abs=1e-12)   # about its own origin
    assert np.degrees(np.linalg.norm(Rot3.Logmap(nominal.rotation().between(turned.rotation())))) == pytest.approx(
        np.degrees(0.01))
    base = world(RigError(stewart_base_offset_m=(0.009, -0.006, 0.004))).world_T_camera()
    assert base.translation() - nominal.translation() == pytest.approx([0.009, -0.006, 0.004], abs=1e-9)
    tilted = world(RigError(stewart_base_rotation_rad=(0.0, 0.01, 0.0))).world_T_camera()
    # the base turns about its own origin: the camera, 0.48 m above it, swings by 4.8 mm along x
    assert tilted.translation()[0] - nominal.translation()[0] == pytest.approx(0.48 * math.sin(0.01), abs=2e-4)


def test_the_structure_turns_about_the_true_axis():
    d = np.array([0.002, -0.0015])
    w0, w = world(RigError()), world(RigError(turntable_axis_offset_m=tuple(d)))
    assert w.world_T_structure().equals(w0.world_T_structure(), 1e-12)        # encoder zero = the world frame
    for ww in (w0, w):
        ww.turntable.set_position(math.pi)
    # a point on the designed axis turns half a circle about the true one: it lands 2 d away
    axis_point_structure = w0.world_T_structure().inverse().transformFrom(np.zeros(3))
    moved = w.world_T_structure().transformFrom(axis_point_structure)
    assert moved[:2] == pytest.approx(2 * d, abs=1e-9)
    t = world(RigError(turntable_axis_tilt_rad=(0.0004, 0.0)))
    t.turntable.set_position(math.pi)
    up = t.world_T_structure().transformFrom(axis_point_structure + [0, 0, 1.0])
    assert abs(up[1]) == pytest.approx(2 * math.sin(0.0004), rel=1e-3)        # a tilted axis sweeps a cone


def test_lens_errors_change_the_true_camera_only():
    w = world(RigError(focal_scale=1.004, principal_point_offset_px=(2.0, -1.5)))
    c = RIG.sim.camera
    assert w.camera.K[0, 0] == pytest.approx(c["fx_px"] * 1.004)
    assert w.camera.K[:2, 2] == pytest.approx([c["cx_px"] + 2.0, c["cy_px"] - 1.5])


def test_turntable_tags_are_glued_with_seeded_errors_and_modules_are_not():
    err = RigError(turntable_tag_sigma_m=0.001)
    a, b, c = world(err, seed=3), world(err, seed=3), world(err, seed=4)
    model = a.borg.model
    offs = np.array([a.borg.structure_T_tag(t).translation() - model.tags[t].structure_T_tag.translation()
                     for t in model.turntable.tag_ids])
    assert 0.0003 < offs.std() < 0.003
    assert all(a.borg.structure_T_tag(t).equals(b.borg.structure_T_tag(t), 0) for t in model.turntable.tag_ids)
    assert not a.borg.structure_T_tag(36).equals(c.borg.structure_T_tag(36), 1e-6)
    assert a.borg.structure_T_tag(0).equals(model.tags[0].structure_T_tag, 1e-12)


def test_every_move_lands_with_its_own_repeatability_error_and_a_reseed_repeats_it():
    err = RigError(turntable_repeatability_rad=1e-4, stewart_repeatability_m=2e-5, stewart_repeatability_rad=3e-5)
    w = world(err)
    first = w.turntable_angle_rad()
    assert first == w.turntable_angle_rad()                 # no move, same error
    w.turntable.start(0.0)
    second = w.turntable_angle_rad()
    assert second != first and abs(second) < 1e-3
    cams = []
    for _ in range(2):
        w.reseed_camera([0, 1, 2])
        cams.append((w.turntable_angle_rad(), w.world_T_camera()))
    assert cams[0][0] == cams[1][0] and cams[0][1].equals(cams[1][1], 0)
    w.stewart_legs.start(w.stewart_legs.target())
    assert not w.world_T_camera().equals(cams[1][1], 1e-9)


def test_the_software_is_not_told_the_rig_error():
    from sim_devices.bench import start_sim_bench

    with start_sim_bench(RIG, Scenario()) as bench:
        assert bench.world.rig_error == RIG.sim.rig_error
        assert bench.rig.sim.rig_error.ideal
        assert "rig_error" not in bench.rig.data["sim"]


def test_a_sim_table_without_rig_error_means_an_ideal_rig():
    from lab.core.config import SimConfig, parse_rig
    import tomllib
    from lab.core.config import default_rig_path

    assert SimConfig().rig_error == RigError()            # the record, not the rig-file exception
    data = tomllib.loads(default_rig_path().read_text())
    data["sim"].pop("rig_error")
    assert parse_rig(data, "r.toml", default_rig_path().parent).sim.rig_error.ideal
