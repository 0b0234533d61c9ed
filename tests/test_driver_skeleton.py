"""Every driver says what it is (drivers/driver.py): its kind, whether it moves, its own check;
`drivers/devices.py` asks the driver and never switches on the kind."""

from __future__ import annotations

from typing import get_args

from drivers.devices import DRIVERS, connect
from drivers.driver import Actuator, Driver
from drivers.testing import fast_sim_rig
from lab.core.config import DeviceKind


def test_every_kind_of_device_a_rig_names_has_its_driver():
    assert set(DRIVERS) == set(get_args(DeviceKind))
    for kind, cls in DRIVERS.items():
        assert issubclass(cls, Driver) and cls.kind == kind
        assert cls.moves == issubclass(cls, Actuator)        # only the camera does not move
    assert not DRIVERS["camera"].moves


def test_connect_opens_each_device_with_the_driver_its_kind_names_in_the_rigs_order():
    rig = fast_sim_rig()
    with connect(rig, claim=False) as devs:
        assert [(n, type(d)) for n, d in devs.all()] == [(n, DRIVERS[k]) for n, k, _ in rig.devices()]
        assert devs.turntable is devs[rig.turntable.name] and devs.camera is devs[rig.camera.name]
        assert list(devs.ipjrs) == list(rig.ipjrs)
    with connect(rig, only=[rig.camera.name], claim=False) as devs:
        assert devs.turntable is None and devs.ipjrs == {} and devs.camera is not None
