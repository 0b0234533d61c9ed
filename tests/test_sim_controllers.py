"""The simulated serial controllers share one skeleton (sim_devices/controller.py): ID?, STOP,
CLEAR, the fault latch, the state, link loss.  What each device keeps is its own."""

from __future__ import annotations

import json

import numpy as np

from sim_devices.controller import AxisController, Controller
from sim_devices.ipjr import IpjrActuator, IpjrSerialSim, ipjr_routes
from sim_devices.lift import LiftSim
from sim_devices.motion import Axis
from sim_devices.turntable import TurntableSim


def _actuator() -> IpjrActuator:
    return IpjrActuator("ipjr1", stroke_m=0.14, step_m=0.000138, axis=Axis(0.07, 0.01, 0.05), volts_retracted=0.5,
                        volts_extended=4.5, volts_noise_v=0.0, step_scale=1.0, move_sigma_m=0.0,
                        rng=np.random.default_rng(0))


def test_the_ipjrs_serial_clear_clears_the_latch_its_http_front_end_reads():
    act = _actuator()
    serial, http = IpjrSerialSim(act), ipjr_routes(act)
    assert isinstance(serial, Controller)
    act.fault = "overheat"
    assert serial.handle("STATUS?").startswith("OK state=FAULT") and serial.handle("STEP 3").startswith("ERR 40")
    assert serial.handle("CLEAR") == "OK"
    assert act.fault == "none" and json.loads(http["/status"]({}, False)[2])["fault"] == "none"


def test_single_axis_controllers_speak_their_own_units_through_one_skeleton():
    t = [0.0]
    lift = LiftSim(Axis(0.0, 1.0, 0.0, lambda: t[0]), -600.0, 2600.0)
    table = TurntableSim(Axis(0.5, np.radians(30.0), 0.0, lambda: t[0]), -360.0, 360.0)
    assert isinstance(lift, AxisController) and isinstance(table, AxisController)
    assert lift.handle("LIMITS?") == "OK min_mm=-600.000 max_mm=2600.000 speed_mm_s=1000.000 settle_s=0.000"
    assert table.handle("LIMITS?") == "OK min_deg=-360.000 max_deg=360.000 speed_deg_s=30.000 settle_s=0.000"
    assert lift.handle("MOVE 3000") == "ERR 20 height 3000.000 mm outside [-600.000, 2600.000] mm"
    assert table.handle("MOVE 10") == "ERR 30 not homed: send HOME first"
    assert table.handle("HOME") == "OK" and table.handle("MOVE 10").startswith("ERR 31")   # busy homing
    assert table.handle("STATUS?") == "OK state=HOMING pos_deg=28.648 target_deg=0.000 homed=0 fault=none"
    assert lift.handle("MOVE 500") == "OK" and lift.handle("STATUS?").startswith("OK state=MOVING")
    lift.link_lost()
    assert lift.handle("STATUS?") == "OK state=IDLE pos_mm=0.000 target_mm=0.000 fault=none"


def test_a_homing_run_that_ended_unpolled_survives_its_host_leaving():
    # The table latches its home when the motion ends; a host that drops the link after that,
    # without having asked STATUS?, must not leave it un-homed (the CI flake of stop 49).
    t = [0.0]
    table = TurntableSim(Axis(0.5, np.radians(30.0), 0.1, lambda: t[0]), -360.0, 360.0)
    assert table.handle("HOME") == "OK"
    t[0] = 10.0                      # travel and settling long over; nobody polled
    table.link_lost()
    assert table.homed and table.handle("MOVE 10") == "OK"


def test_a_host_that_leaves_mid_homing_leaves_the_table_unhomed():
    t = [0.0]
    table = TurntableSim(Axis(0.5, np.radians(30.0), 0.1, lambda: t[0]), -360.0, 360.0)
    assert table.handle("HOME") == "OK"
    t[0] = 0.5                       # still turning
    table.link_lost()
    assert not table.homed and table.handle("MOVE 10").startswith("ERR 30")
