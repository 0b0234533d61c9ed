"""Injected faults end in a clear error or a recovery, never a hang, and with motion stopped."""

from __future__ import annotations

import dataclasses
import math
import re
import time

import pytest

import drivers
from drivers.camera import Camera
from drivers.errors import DeviceFault, DeviceTimeout, Disconnected, LengthControlError, ProtocolError
from drivers.testing import fast_sim_rig
from lab.core.comms import MemoryComms
from lab.core.errors import UserError
from lab.core.scenario import DeviceFault as ScenarioFault
from lab.core.scenario import Scenario
from sim_devices.bench import start_sim_bench

RIG = fast_sim_rig()     # reply timeout 0.25 s, motion margin 0.2 s, 2 retries


@pytest.fixture
def bench():
    with start_sim_bench(RIG, speedup=1000) as b:
        yield b


@pytest.fixture
def slow_bench():
    """Moves that take long enough (tenths of a second) for a fault to land mid-move."""
    with start_sim_bench(RIG, speedup=20) as b:
        yield b


def events(comms: MemoryComms) -> str:
    return " | ".join(r.note for r in comms.records if r.direction == "event")


def tx(comms: MemoryComms, device: str) -> list[bytes]:
    """Requests sent to a device, without their tags (`#7 STOP\n` -> `STOP\n`)."""
    return [re.sub(rb"^#\d+ ", b"", r.data) for r in comms.records if r.direction == "tx" and r.device == device]


class Deadline:
    def __init__(self, seconds: float) -> None:
        self.seconds = seconds

    def __enter__(self):
        self.t0 = time.monotonic()
        return self

    def __exit__(self, *exc) -> None:
        elapsed = time.monotonic() - self.t0
        assert elapsed < self.seconds, f"took {elapsed:.2f} s (bound {self.seconds} s)"


# ---- turntable --------------------------------------------------------------------------------------
def test_lost_move_command_times_out_and_the_turntable_is_stopped(bench):
    comms = MemoryComms()
    with drivers.connect(bench.rig, comms) as d:
        d.turntable.home()
        bench.inject("turntable", "timeout", after_commands=1)     # STATUS? passes, MOVE is lost
        with Deadline(2), pytest.raises(DeviceTimeout) as err:
            d.turntable.move_to(math.radians(90))
    assert "no reply to 'MOVE 90.000'" in str(err.value) and "motion stopped" in str(err.value)
    assert tx(comms, "turntable")[-1] == b"STOP\n"
    assert not bench.world.turntable.moving() and float(bench.world.turntable.position()) == pytest.approx(0.0)


def test_one_lost_query_reply_is_recovered_by_a_retry(bench):
    comms = MemoryComms()
    with drivers.connect(bench.rig, comms) as d:
        bench.inject("turntable", "timeout", count=1)
        with Deadline(2):
            assert d.turntable.position() == pytest.approx(0.0)
    assert "retry 1/2 of 'POS?'" in events(comms)


def test_a_dead_turntable_gives_a_clear_error_that_says_it_may_still_move(bench):
    with drivers.connect(bench.rig) as d:
        d.turntable.home()
        bench.inject("turntable", "timeout", after_commands=1, count=0)   # dead after STATUS?
        with Deadline(4), pytest.raises(DeviceTimeout) as err:
            d.turntable.move_to(math.radians(45))
    assert "STOP failed too" in str(err.value) and "may still be moving" in str(err.value)


def test_garbled_query_is_retried_and_garbled_move_reply_stops_the_turntable(slow_bench):
    comms = MemoryComms()
    with drivers.connect(slow_bench.rig, comms) as d:
        slow_bench.inject("turntable", "garbled", count=1)
        assert d.turntable.position() == pytest.approx(0.0)            # recovered
        assert "is not ASCII" in events(comms)
        d.turntable.home()
        slow_bench.inject("turntable", "garbled", after_commands=1)     # the MOVE's reply
        with Deadline(2), pytest.raises(ProtocolError) as err:
            d.turntable.move_to(math.radians(180))
    assert "reply to 'MOVE 180.000' is not ASCII" in str(err.value) and "motion stopped" in str(err.value)
    time.sleep(0.05)
    assert not slow_bench.world.turntable.moving()
    assert math.degrees(slow_bench.world.turntable_angle_rad()) < 179.0   # it had started, then stopped


def test_dropped_connection_mid_move_reconnects_and_reports_where_it_stopped(slow_bench):
    comms = MemoryComms()
    with drivers.connect(slow_bench.rig, comms) as d:
        d.turntable.home()
        slow_bench.inject("turntable", "disconnect")        # fires on the first command while moving
        with Deadline(3), pytest.raises(Disconnected) as err:
            d.turntable.move_to(math.radians(120))
    # the link loss is named as such, with where the turntable stopped
    assert "link to socket://" in str(err.value) and "lost during the move" in str(err.value)
    assert "short of the target 120.000 deg" in str(err.value)
    assert "link lost" in events(comms) and events(comms).count("opened") >= 2
    assert not slow_bench.world.turntable.moving()


def test_stuck_turntable_times_out_from_the_physics_and_is_stopped(bench):
    with drivers.connect(bench.rig) as d:
        d.turntable.home()
        bench.inject("turntable", "stuck")
        with Deadline(2), pytest.raises(DeviceTimeout) as err:
            d.turntable.move_to(math.radians(90))
    msg = str(err.value)
    assert "move to 90.000 deg not finished within" in msg and "at 0.000 deg" in msg and "motion stopped" in msg
    assert not bench.world.turntable.moving()


# ---- Stewart ----------------------------------------------------------------------------------------
def test_stuck_stewart_times_out_and_is_stopped(bench):
    with drivers.connect(bench.rig) as d:
        bench.inject("stewart", "stuck")
        with Deadline(2), pytest.raises(DeviceTimeout, match="not finished within .*motion stopped"):
            d.stewart.move_to([0, 0, 0.03, 0, 0.05, 0])
    assert not bench.world.stewart_legs.moving()


def test_lost_legs_command_stops_the_stewart(bench):
    comms = MemoryComms()
    with drivers.connect(bench.rig, comms) as d:
        d.stewart.hardware()
        bench.inject("stewart", "timeout", after_commands=1)     # LEGS? passes, LEGS is lost
        with Deadline(2), pytest.raises(DeviceTimeout, match="motion stopped"):
            d.stewart.move_to([0.02, 0, 0, 0, 0, 0])
    assert tx(comms, "stewart")[-1] == b"STOP\n"


# ---- IPJR -------------------------------------------------------------------------------------------
def attached(d, bench, name: str, length: float = 0.80):
    bench.world.ipjrs[name].attach(length)      # the operator clamps it on a strut...
    d.ipjrs[name].attach(length)                # ...and measures the strut with a ruler
    return d.ipjrs[name]


def test_http_500_on_a_read_is_retried_and_on_a_step_stops_the_ipjr(bench):
    comms = MemoryComms()
    with drivers.connect(bench.rig, comms) as d:
        ipjr = attached(d, bench, "ipjr1")
        bench.inject("ipjr1", "http_500", count=1)
        assert 0 < ipjr.volts() < 5                                         # recovered
        ipjr.hardware()
        bench.inject("ipjr1", "http_500", after_commands=4)                 # 4 volts reads, then /step
        with Deadline(2), pytest.raises(DeviceFault) as err:
            ipjr.set_length(0.81)
    assert err.value.code == 500 and "motion stopped" in str(err.value)
    assert not bench.world.ipjrs["ipjr1"].moving()


def test_hung_http_step_times_out_and_stops(bench):
    with drivers.connect(bench.rig) as d:
        ipjr = attached(d, bench, "ipjr2")
        ipjr.hardware()
        bench.inject("ipjr2", "timeout", after_commands=4)
        with Deadline(3), pytest.raises(DeviceTimeout, match=r"no reply to GET /step\?steps=-?\d+ .*motion stopped"):
            ipjr.set_length(0.79)
    assert not bench.world.ipjrs["ipjr2"].moving()


def test_length_controller_recovers_from_a_dropped_connection_mid_move(slow_bench):
    comms = MemoryComms()
    with drivers.connect(slow_bench.rig, comms) as d:
        ipjr = attached(d, slow_bench, "ipjr1")
        slow_bench.inject("ipjr1", "disconnect")     # the Pi drops a /moving poll; the actuator stops
        with Deadline(10):
            result = ipjr.set_length(0.83)
    assert abs(result.error_m) < 0.5e-3 and result.tries >= 2        # it re-measured and went on
    assert abs(slow_bench.world.ipjrs["ipjr1"].strut_length_m() - 0.83) < 1e-3
    assert "link lost" in events(comms)


def test_stuck_ipjr_times_out_and_is_stopped(bench):
    with drivers.connect(bench.rig) as d:
        ipjr = attached(d, bench, "ipjr3")      # the serial (Arduino) transport
        bench.inject("ipjr3", "stuck")
        with Deadline(3), pytest.raises(DeviceTimeout, match="not finished within .*motion stopped"):
            ipjr.set_length(0.82)
    assert not bench.world.ipjrs["ipjr3"].moving()


def test_length_controller_stops_when_the_true_step_is_too_large(bench):
    """The paper: the controller diverges if the actual step is larger than the estimated one (here 2.6x)."""
    bench.world.ipjrs["ipjr3"].step_scale = 2.6
    with drivers.connect(bench.rig) as d:
        ipjr = attached(d, bench, "ipjr3")
        with Deadline(5), pytest.raises(LengthControlError) as err:
            ipjr.set_length(0.81)
    assert "diverging" in str(err.value) and "motion stopped" in str(err.value)
    errors = [abs(0.81 - m) for _, m in err.value.history]
    assert errors[-1] > errors[0]
    assert not bench.world.ipjrs["ipjr3"].moving()


# ---- camera -----------------------------------------------------------------------------------------
def fast_camera(bench, comms=None) -> Camera:
    return Camera(dataclasses.replace(bench.rig.camera, timeout_s=0.5), comms or MemoryComms())


def test_camera_recovers_from_one_500_and_one_garbled_frame(bench):
    comms = MemoryComms()
    cam = fast_camera(bench, comms)
    bench.inject("camera", "http_500", count=1)
    assert cam.grab().image.shape == (720, 1280, 3)
    bench.inject("camera", "garbled", count=1)
    assert cam.grab().image.shape == (720, 1280, 3)
    assert "not an image" in events(comms)


def test_camera_that_stops_answering_is_a_clear_timeout(bench):
    cam = fast_camera(bench)
    bench.inject("camera", "timeout", count=0)
    with Deadline(3), pytest.raises(DeviceTimeout, match=r"no reply to GET /frame.jpg within 0.5 s"):
        cam.grab()


# ---- faults from a scenario file --------------------------------------------------------------------
def test_scenario_device_faults_are_armed_and_checked():
    scenario = Scenario(seed=3, device_faults=(ScenarioFault("turntable", "timeout", after_commands=2, count=1),))
    with start_sim_bench(RIG, scenario, speedup=1000) as b:
        comms = MemoryComms()
        with drivers.connect(b.rig, comms) as d:
            for _ in range(3):
                d.turntable.position()
        assert b.faults["turntable"].log == [("timeout", "POS?")]
        assert "retry 1/2" in events(comms)
    bad = Scenario(device_faults=(ScenarioFault("turntable", "http_500"),))
    with pytest.raises(UserError, match=r"device.fault\[0\].*http_500 needs an HTTP device"):
        start_sim_bench(RIG, bad)
    bad = Scenario(device_faults=(ScenarioFault("laser", "timeout"),))
    with pytest.raises(UserError, match=r"device.fault\[0\].device: no device 'laser'"):
        start_sim_bench(RIG, bad)
