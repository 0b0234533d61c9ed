"""The lift (the vertical stage under the Stewart base): its driver against scripted bytes and
against its simulator over the real transports, and what its moves do to the simulated camera."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from drivers.errors import DeviceFault, OutOfRange, RigMismatch
from drivers.lift import Lift
from drivers.testing import ScriptedLineDevice, fast_sim_rig
from lab.core.comms import MemoryComms
from lab.core.config import load_rig
from lab.core.geometry import Pose3, Rot3
from lab.core.rig_error import RigError
from lab.core.scenario import Scenario
from sim_devices.bench import start_sim_bench

RIG = load_rig()
LIMITS = b"OK min_mm=-600.000 max_mm=4600.000 speed_mm_s=1000.000 settle_s=0.000\n"
# the bench (tests/conftest.py) also serves each serial device on a pty: the driver over a real tty
pytestmark = pytest.mark.sim_bench(pty=True)


def lift_on(url: str, comms=None) -> Lift:
    return Lift.open(RIG.with_urls({"lift": url}).lift, comms or MemoryComms())


def status(state: str, pos_mm: float, target_mm: float) -> bytes:
    return f"OK state={state} pos_mm={pos_mm:.3f} target_mm={target_mm:.3f} fault=none\n".encode()


def test_move_is_limits_status_move_then_polls_until_idle():
    with ScriptedLineDevice([
        (b"LIMITS?\n", LIMITS),
        (b"STATUS?\n", status("IDLE", 0, 0)),
        (b"MOVE 1250.000\n", b"OK\n"),
        (b"STATUS?\n", status("MOVING", 600, 1250)),
        (b"STATUS?\n", status("IDLE", 1250, 1250)),
    ]) as dev:
        assert lift_on(dev.url).move_to(1.25) == pytest.approx(1.25)


def test_out_of_range_heights_never_reach_the_wire():
    with ScriptedLineDevice([]) as dev:                   # any byte sent would fail the script
        comms = MemoryComms()
        lift = lift_on(dev.url, comms)
        for bad in (-0.6, 4.51, float("nan"), float("inf")):
            with pytest.raises(OutOfRange, match=r"lift height .* outside the limits \[-0.5, 4.5\] m .*nothing was sent"):
                lift.move_to(bad)
        assert not [r for r in comms.records if r.direction == "tx"] and not lift.moved
        lift.check_height(4.5)


def test_an_err_reply_is_a_typed_fault_and_nothing_more_is_sent():
    with ScriptedLineDevice([
        (b"LIMITS?\n", LIMITS),
        (b"STATUS?\n", status("IDLE", 0, 0)),
        (b"MOVE 500.000\n", b"ERR 40 fault stalled latched: send CLEAR after finding the cause\n"),
    ]) as dev:
        lift = lift_on(dev.url)
        with pytest.raises(DeviceFault) as err:
            lift.move_to(0.5)
        assert err.value.code == 40 and not lift.moved     # a clean refusal moved nothing


def test_home_move_position_and_the_camera_rises_with_it(bench):
    lift = Lift.open(bench.rig.lift, MemoryComms())
    assert lift.identify() == "LIFT LAB-LZ1 1.0"
    cam0 = bench.world.world_T_camera()
    fractions: list[float] = []
    assert lift.move_to(1.2, progress=fractions.append) == pytest.approx(1.2)
    assert fractions and fractions[-1] == pytest.approx(1.0)
    assert lift.position() == pytest.approx(1.2) and lift.status().state == "IDLE"
    rise = bench.world.world_T_camera().translation() - cam0.translation()
    # 1.2 m up the lift's true axis, tilted (sim rig [sim.rig_error]) by ~0.5 mm per metre
    assert rise[2] == pytest.approx(1.2, abs=1e-4)
    assert 0.3e-3 < np.hypot(rise[0], rise[1]) < 1.0e-3
    assert lift.home() == pytest.approx(0.0)
    lift.close()


def test_a_lift_that_never_moved_leaves_the_camera_where_the_rig_file_puts_it():
    """A run that needs no lift move (the 3x3x3 cube) sees exactly the bench it saw before the
    lift existed: no tilt, no repeatability error."""
    with start_sim_bench(fast_sim_rig(), speedup=1000) as b:
        rig = b.world.true_rig
        legs_home = b.world.home_T_platform()
        expected = rig.world_T_base.compose(Pose3(legs_home.rotation(), RIG.stewart.geometry.home_m
                                                  + legs_home.translation())).compose(
            b.world._stewart_repeatability()).compose(rig.platform_T_camera)
        assert b.world.world_T_camera().equals(expected, 1e-12)
        assert not b.world.lift_offset_m().any()


def test_an_ideal_lift_moves_the_base_straight_up():
    with start_sim_bench(fast_sim_rig(), Scenario(seed=0, rig_error=RigError()), speedup=1000) as b:
        lift = Lift.open(b.rig.lift)
        lift.move_to(-0.4)
        assert b.world.lift_offset_m() == pytest.approx([0.0, 0.0, -0.4], abs=1e-12)
        assert b.world.true_rig.world_T_lift.equals(Pose3(Rot3(), np.zeros(3)), 1e-15)
        lift.close()


def test_rig_limits_wider_than_the_hardware_are_a_rig_mismatch(bench):
    cfg = dataclasses.replace(bench.rig.lift, max_m=5.0)
    lift = Lift.open(cfg)
    with pytest.raises(RigMismatch, match=r"rig limits \[-500, 5000\] mm exceed the hardware travel \[-600, 4600\] mm"):
        lift.move_to(0.1)
    lift.close()


def test_the_device_refuses_out_of_travel_and_busy_moves(bench):
    lift = Lift.open(bench.rig.lift)
    with pytest.raises(DeviceFault, match=r"height 4700.000 mm outside \[-600.000, 4600.000\] mm") as err:
        lift.link.request("MOVE 4700", idempotent=False)
    assert err.value.code == 20
    lift.close()
    with start_sim_bench(fast_sim_rig(), speedup=5) as slow:
        lift = Lift.open(slow.rig.lift)
        lift.link.request("MOVE 2000.000", idempotent=False)
        with pytest.raises(DeviceFault) as err:
            lift.link.request("MOVE 10.000", idempotent=False)
        assert err.value.code == 31
        lift.stop()
        assert not lift.status().moving and 0 < lift.position() < 2.0
        lift.close()


def test_tagged_requests_over_a_pseudo_terminal(bench):
    cfg = dataclasses.replace(bench.rig.lift, link=dataclasses.replace(bench.rig.lift.link, url=bench.pty_paths["lift"]))
    comms = MemoryComms()
    lift = Lift.open(cfg, comms)
    assert lift.move_to(0.25) == pytest.approx(0.25)
    sent = [r.data for r in comms.records if r.direction == "tx"]
    assert any(b"MOVE 250.000" in d and d.startswith(b"#") for d in sent)    # `#17 MOVE 250.000`
    lift.home()
    lift.close()
