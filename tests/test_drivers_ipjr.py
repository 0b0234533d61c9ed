"""IPJR driver against the simulated IPJR over both transports (HTTP to the Pi, serial to the
Arduino): calibration, steps, stroke limits, the paper's length controller."""

from __future__ import annotations

import time

import pytest

from drivers.errors import OutOfRange
from drivers.ipjr import Ipjr
from drivers.testing import fast_sim_rig
from lab.core.comms import MemoryComms
from sim_devices.bench import start_sim_bench


def attach(bench, name: str, length: float) -> Ipjr:
    bench.world.ipjrs[name].attach(length)
    ipjr = Ipjr.open(bench.rig.ipjrs[name], MemoryComms())
    ipjr.attach(length)
    return ipjr


def test_calibration_maps_the_stroke_ends():
    rig = fast_sim_rig()
    ipjr = Ipjr.open(rig.ipjrs["ipjr1"])
    assert ipjr.extension_from_volts(0.020) == pytest.approx(0.0)
    assert ipjr.extension_from_volts(4.975) == pytest.approx(0.140)
    assert ipjr.extension_from_volts(2.4975) == pytest.approx(0.070)


@pytest.mark.parametrize("name", ["ipjr1", "ipjr3"])   # HTTP to the Pi, serial to the Arduino
def test_length_controller_sets_the_true_strut_length(bench, name):
    ipjr = attach(bench, name, 0.800)
    assert ipjr.identify().startswith("IPJR")
    truth = bench.world.ipjrs[name]
    tries = []
    for target in (0.790, 0.8431, 0.8012, 0.7655):
        result = ipjr.set_length(target)
        tries.append(result.tries)
        assert abs(result.error_m) < 0.5e-3                          # what the IPJR measures
        assert abs(truth.strut_length_m() - target) < 0.8e-3         # the truth, with calibration error
    assert max(tries) <= 3      # the paper: "converged almost always within three steps"
    assert not ipjr.moving()


def test_steps_past_the_stroke_are_refused_before_sending(bench):
    ipjr = attach(bench, "ipjr2", 0.800)
    comms = MemoryComms()
    ipjr.link.sink = comms
    ext = ipjr.measure_extension()
    before = len([r for r in comms.records if r.direction == "tx"])
    with pytest.raises(OutOfRange, match=r"extension after the move .* mm is outside the limits \[0, 140\] mm"):
        ipjr.step(int((0.140 - ext) / 0.000138) + 20, extension_m=ext)
    lo, hi = ipjr.length_limits_m()
    with pytest.raises(OutOfRange, match="strut length"):
        ipjr.set_length(hi + 0.001)
    assert len([r for r in comms.records if r.direction == "tx"]) == before      # nothing at all sent
    with pytest.raises(ValueError, match="non-zero integer"):
        ipjr.step(0)


def test_length_needs_an_attached_strut(bench):
    ipjr = Ipjr.open(bench.rig.ipjrs["ipjr1"])
    with pytest.raises(RuntimeError, match=r"not attached to a strut: call attach"):
        ipjr.set_length(0.8)


def test_stop_halts_a_move_over_both_transports():
    with start_sim_bench(fast_sim_rig(), speedup=2) as slow:
        for name in ("ipjr1", "ipjr3"):
            ipjr = Ipjr.open(slow.rig.ipjrs[name])
            ipjr.wire.step(-300)                 # 41 mm at 20 mm/s: 2 s
            time.sleep(0.05)
            assert ipjr.moving()
            ipjr.stop()
            assert not ipjr.moving() and not slow.world.ipjrs[name].moving()
            assert ipjr.status()["state"] == "idle"
