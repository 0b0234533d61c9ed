"""Turntable driver against its simulator over the real transport (socket and pseudo-terminal)."""

from __future__ import annotations

import dataclasses
import math

import pytest

from drivers.errors import DeviceFault, OutOfRange, RigMismatch
from drivers.turntable import Turntable
from drivers.testing import fast_sim_rig
from lab.core.comms import MemoryComms
from sim_devices.bench import start_sim_bench

# the bench (tests/conftest.py) also serves each serial device on a pty: the driver over a real tty
pytestmark = pytest.mark.sim_bench(pty=True)


def test_home_move_position_and_world_truth(bench):
    tt = Turntable.open(bench.rig.turntable, MemoryComms())
    assert tt.identify().startswith("TURNTABLE")
    tt.ensure_homed()
    assert tt.status().homed
    fractions: list[float] = []
    reached = tt.move_to(math.radians(90), progress=fractions.append)
    assert reached == pytest.approx(math.pi / 2, abs=1e-4)
    assert bench.world.turntable_angle_rad() == pytest.approx(math.pi / 2, abs=1e-4)   # really turned
    assert fractions and fractions[-1] == pytest.approx(1.0)
    assert tt.position() == pytest.approx(math.pi / 2, abs=1e-4)
    tt.move_to(math.radians(-30))
    assert tt.status().state == "IDLE"
    tt.close()


def test_rig_limits_are_checked_before_sending(bench):
    comms = MemoryComms()
    tt = Turntable.open(bench.rig.turntable, comms)
    for bad in (math.radians(-91), math.radians(361), float("nan")):
        with pytest.raises(OutOfRange, match=r"turntable angle .* outside the limits \[-90, 360\] deg"):
            tt.move_to(bad)
    assert not [r for r in comms.records if r.direction == "tx"]
    tt.check_angle(math.radians(359.9))


def test_rig_limits_wider_than_the_hardware_are_a_rig_mismatch(bench):
    cfg = dataclasses.replace(bench.rig.turntable, max_rad=math.radians(400))
    tt = Turntable.open(cfg)
    with pytest.raises(RigMismatch, match=r"rig limits \[-90, 400\] deg exceed the hardware travel \[-360, 360\] deg"):
        tt.move_to(math.radians(10))


def test_the_device_refuses_a_move_while_another_is_running():
    with start_sim_bench(fast_sim_rig(), speedup=5) as slow:
        tt = Turntable.open(slow.rig.turntable)
        tt.home()
        tt.link.request("MOVE 200.000", idempotent=False)
        with pytest.raises(DeviceFault) as err:
            tt.link.request("MOVE 10.000", idempotent=False)
        assert err.value.code == 31
        tt.stop()
        assert not tt.status().moving
        tt.close()


def test_the_same_driver_over_a_pseudo_terminal(bench):
    cfg = dataclasses.replace(bench.rig.turntable,
                              link=dataclasses.replace(bench.rig.turntable.link, url=bench.pty_paths["turntable"]))
    tt = Turntable.open(cfg, MemoryComms())
    assert tt.identify() == "TURNTABLE LAB-RT1 1.0"
    tt.ensure_homed()
    assert tt.move_to(math.radians(12.5)) == pytest.approx(math.radians(12.5), abs=1e-4)
    tt.close()


def test_ctrl_c_while_waiting_stops_the_turntable():
    with start_sim_bench(fast_sim_rig(), speedup=5) as slow:
        tt = Turntable.open(slow.rig.turntable)
        tt.home()

        def interrupt(fraction: float) -> None:
            raise KeyboardInterrupt

        with pytest.raises(KeyboardInterrupt) as err:
            tt.move_to(math.radians(200), progress=interrupt)
        assert any("motion stopped" in note for note in getattr(err.value, "__notes__", []))
        assert not slow.world.turntable.moving() and slow.world.turntable_angle_rad() < math.radians(100)
        tt.close()
